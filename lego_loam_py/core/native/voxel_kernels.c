/*
 * The voxel filter of core/voxel.py in one pass, with the NumPy version's float32 arithmetic operation by operation
 * (built with -ffp-contract=off: no fused multiply-adds). core/voxel.py keeps its NumPy code as the fallback when
 * this extension is not built, and tests/test_voxel.py compares the two bit for bit.
 *
 * voxel_groups(points, group_starts, inverse, out, counts) -> m
 *   points (n, k >= 3) float32, C-contiguous, finite x, y, z, its groups contiguous and in order; group_starts
 *   (g,) int64, ascending from 0: each group's first row. Each group on its own grid, as voxel_downsample_groups:
 *   a point's cell is floor(p * inverse) per axis (float32), numbered x-fastest from the group's lowest cell; one
 *   output row per occupied cell, groups in order and cells by number within a group, the mean of its points'
 *   columns. The sums are those of np.add.reduceat over the cell's points in their input order: the first point
 *   plus NumPy's pairwise sum of the others (below 8 values a plain sum from -0.0; up to 128, eight interleaved
 *   partial sums combined as ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7)) and the rest added; beyond, the
 *   two halves split at a multiple of 8). Writes out (m, k) float32 and counts (m,) int64; returns m, or -1
 *   (nothing usable written) for a group whose cells and points cannot be packed into one 63-bit sort key (a
 *   grid of some 10^18 cells: the caller then filters with NumPy). Runs without the GIL.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "radix_sort.h"

/* floorf, inline: exact, as floor is; its zero may lose the sign, which no use of it here sees (cells are
   differences of floors, converted to integers). */
static inline float floor_exact(float x) {
    if (!(fabsf(x) < 8388608.0f)) return x; /* 2^23 and beyond: already an integer (or not finite) */
    const float t = (float)(int32_t)x;
    return t > x ? t - 1.0f : t;
}

/* Ascending sort of distinct 64-bit keys: quicksort (median of three) down to short runs, then insertion sort. */
static void sort_keys(uint64_t *a, int64_t n) {
    while (n > 16) {
        uint64_t x = a[0], y = a[n / 2], z = a[n - 1];
        uint64_t pivot = x < y ? (y < z ? y : (x < z ? z : x)) : (x < z ? x : (y < z ? z : y));
        int64_t i = 0, j = n - 1;
        for (;;) {
            while (a[i] < pivot) ++i;
            while (a[j] > pivot) --j;
            if (i >= j) break;
            uint64_t t = a[i];
            a[i] = a[j];
            a[j] = t;
            ++i;
            --j;
        }
        /* [0, j] <= pivot <= [j + 1, n): recurse into the smaller side, loop on the larger */
        if (j + 1 < n - j - 1) {
            sort_keys(a, j + 1);
            a += j + 1;
            n -= j + 1;
        } else {
            sort_keys(a + j + 1, n - j - 1);
            n = j + 1;
        }
    }
    for (int64_t i = 1; i < n; ++i) {
        uint64_t v = a[i];
        int64_t j = i - 1;
        while (j >= 0 && a[j] > v) {
            a[j + 1] = a[j];
            --j;
        }
        a[j + 1] = v;
    }
}

/* Ascending sort of distinct keys whose bits below `low_bits` ascend already where the bits above them tie (a
   point's place in its group under its cell number): a radix sort of the bits from low_bits up to `high_bits`, for
   groups long enough to repay its counts (the same order as sort_keys). */
static void sort_cells(uint64_t *a, uint64_t *scratch, int64_t n, int low_bits, int high_bits) {
    if (n < 256 || high_bits <= low_bits) {
        sort_keys(a, n);
        return;
    }
    const uint64_t *sorted = radix_sort_bits(a, scratch, n, low_bits, high_bits);
    if (sorted != a) memcpy(a, sorted, sizeof(uint64_t) * (size_t)n);
}

/* NumPy's pairwise sum of float32 values (its reduction loop for float32 add). */
static float pairwise_sum(const float *a, int64_t n) {
    if (n < 8) {
        float res = -0.0f;
        for (int64_t i = 0; i < n; ++i) res += a[i];
        return res;
    }
    if (n <= 128) {
        float r[8];
        int64_t i;
        for (int j = 0; j < 8; ++j) r[j] = a[j];
        for (i = 8; i < n - (n % 8); i += 8) {
            for (int j = 0; j < 8; ++j) r[j] += a[i + j];
        }
        float res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
        for (; i < n; ++i) res += a[i];
        return res;
    }
    int64_t half = n / 2;
    half -= half % 8;
    return pairwise_sum(a, half) + pairwise_sum(a + half, n - half);
}

static PyObject *py_voxel_groups(PyObject *self, PyObject *args) {
    Py_buffer points, starts, out, counts;
    Py_ssize_t columns;
    float inverse;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*ny*fw*w*", &points, &columns, &starts, &inverse, &out, &counts)) {
        return NULL;
    }
    PyObject *result = NULL;
    const Py_ssize_t k = columns;
    const Py_ssize_t n = k >= 3 ? points.len / (Py_ssize_t)(k * sizeof(float)) : 0;
    const Py_ssize_t groups = starts.len / 8;
    if (k < 3 || points.len != n * k * (Py_ssize_t)sizeof(float) || starts.len != groups * 8 ||
        out.len != points.len || counts.len != n * 8 || (n > 0 && groups == 0)) {
        PyErr_SetString(PyExc_ValueError, "voxel_groups: inconsistent buffer sizes");
        goto done;
    }
    const float *p = points.buf;
    const int64_t *group_start = starts.buf;
    float *o = out.buf;
    int64_t *count = counts.buf;
    int failed = 0;
    int64_t m = 0;
    Py_BEGIN_ALLOW_THREADS
    float *scaled = malloc(sizeof(float) * 3 * (size_t)(n > 0 ? n : 1));
    float *column = malloc(sizeof(float) * (size_t)(n > 0 ? n : 1));
    uint64_t *key = malloc(sizeof(uint64_t) * (size_t)(n > 0 ? n : 1));
    uint64_t *scratch = malloc(sizeof(uint64_t) * (size_t)(n > 0 ? n : 1));
    if (scaled == NULL || column == NULL || key == NULL || scratch == NULL) {
        failed = 1;
    }
    for (Py_ssize_t g = 0; g < groups && !failed; ++g) {
        const int64_t first = group_start[g], stop = g + 1 < groups ? group_start[g + 1] : (int64_t)n;
        if (first < 0 || stop > (int64_t)n || stop <= first) {
            failed = 2;
            break;
        }
        float low[3], high[3];
        for (int64_t i = first; i < stop; ++i) {
            for (int a = 0; a < 3; ++a) {
                const float s = floor_exact(p[i * k + a] * inverse);
                scaled[3 * i + a] = s;
                if (i == first || s < low[a]) low[a] = s;
                if (i == first || s > high[a]) high[a] = s;
            }
        }
        const int64_t span0 = (int64_t)(high[0] - low[0]) + 1, span1 = (int64_t)(high[1] - low[1]) + 1;
        const int64_t span2 = (int64_t)(high[2] - low[2]) + 1, size = stop - first;
        /* Each point's key: its cell number above the bits of its place in the group. Keys are distinct, and
           their order is the cells' with ties in input order, as NumPy's stable argsort gives. */
        int bits = 0;
        while (bits < 62 && ((int64_t)1 << bits) < size) ++bits;
        if ((double)span0 * (double)span1 * (double)span2 * (double)((int64_t)1 << bits) >= 9.0e18) {
            failed = 3;
            break;
        }
        const uint64_t place = ((uint64_t)1 << bits) - 1;
        uint64_t *group_key = key + first;
        for (int64_t i = first; i < stop; ++i) {
            const int64_t x = (int64_t)(scaled[3 * i] - low[0]), y = (int64_t)(scaled[3 * i + 1] - low[1]);
            const int64_t z = (int64_t)(scaled[3 * i + 2] - low[2]);
            group_key[i - first] = ((uint64_t)(x + y * span0 + z * (span0 * span1)) << bits) | (uint64_t)(i - first);
        }
        int cell_bits = 0; /* (the highest cell number, span0 span1 span2 - 1, fits in these) */
        while (cell_bits < 63 && ((uint64_t)1 << cell_bits) < (uint64_t)(span0 * span1 * span2)) ++cell_bits;
        sort_cells(group_key, scratch, size, bits, bits + cell_bits);
        for (int64_t r = 0; r < size;) {
            const uint64_t cell = group_key[r] >> bits;
            int64_t e = r + 1;
            while (e < size && group_key[e] >> bits == cell) ++e;
            const int64_t c = e - r;
            const float *head = p + (first + (int64_t)(group_key[r] & place)) * k;
            for (Py_ssize_t j = 0; j < k; ++j) {
                float sum = head[j];
                if (c > 1) {
                    for (int64_t q = r + 1; q < e; ++q) {
                        column[q - r - 1] = p[(first + (int64_t)(group_key[q] & place)) * k + j];
                    }
                    sum += pairwise_sum(column, c - 1);
                }
                o[m * k + j] = sum / (float)c;
            }
            count[m] = c;
            ++m;
            r = e;
        }
    }
    free(scaled);
    free(column);
    free(key);
    free(scratch);
    Py_END_ALLOW_THREADS
    if (failed == 1) {
        PyErr_NoMemory();
        goto done;
    }
    if (failed == 2) {
        PyErr_SetString(PyExc_ValueError, "voxel_groups: group starts must ascend from 0 within the points");
        goto done;
    }
    result = PyLong_FromLongLong(failed == 3 ? -1 : m);
done:
    PyBuffer_Release(&points);
    PyBuffer_Release(&starts);
    PyBuffer_Release(&out);
    PyBuffer_Release(&counts);
    return result;
}

static PyMethodDef methods[] = {
    {"voxel_groups", py_voxel_groups, METH_VARARGS, "Voxel centroids of each group of points (see the file)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_voxel_kernels", NULL, -1, methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__voxel_kernels(void) { return PyModule_Create(&module); }
