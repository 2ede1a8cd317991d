/*
 * The occupancy grid's per-keyframe array passes (core/mapping/occupancy_grid.py, occupancy_ground.py) in C, with
 * the NumPy versions' arithmetic operation by operation (built with -ffp-contract=off). Both modules keep their
 * NumPy code as the fallback when this extension is not built, and tests/test_occupancy_grid.py compares the two
 * bit for bit.
 *
 * update_disk(log_odds, observed, width, x0, y0, size, ranges, bins, free_range, hit, hit_value, miss_value, low,
 *             high)
 *   One keyframe's update of the size x size window from column x0, row y0 of the grid's arrays log_odds (h, width)
 *   float32 and observed (h, width) bool, both C-contiguous, in place, as OccupancyGrid's NumPy code: over every
 *   cell of the window (ranges and bins (size, size) float32 and int32: the disk's range [m] and azimuth bin of
 *   each cell; hit (size, size) bool: the keyframe's obstacle cells), free = range < free_range[bin] (float32), the
 *   log-odds get + (hit ? hit_value : free ? miss_value : 0) in float32, then np.clip's
 *   min(max(v, low), high) with NaN passed through, and observed |= hit | free. Returns None; a ValueError for a
 *   window outside the arrays or buffers of the wrong sizes (nothing written then), an IndexError for a bin outside
 *   free_range (the rows before its row updated: the disk is not the grid's own). Runs without the GIL.
 *
 * coarse_cone(grid, columns, di, dj, terms, cells, out)
 *   grid (rows, columns) float64 C-contiguous; di, dj (m,) int64 and terms (m,) float64: a table of cell offsets
 *   and what each adds; cells (k, 2) int64, each a cell of the grid. For each cell (a, b): the minimum, in table
 *   order from +inf, of grid[a - di, b - dj] + terms over the offsets whose cell lies in the grid, as a sequence of
 *   np.minimum (NaN propagates, the first one met kept; on equal values the earlier one kept), into out (k,)
 *   float64. Returns None; an IndexError for a cell outside the grid (nothing usable written). Runs without the GIL.
 *
 * pair_offsets(x, y, first, second, offsets, distance)
 *   For the pairs (first[p], second[p]) (m,) int64 of points with coordinates x, y (n,) float64: offsets (m, 2)
 *   float64 the differences (x[first] - x[second], y[first] - y[second]) and distance (m,) float64 their hypot (the
 *   C library's, as np.hypot's float64 loop). Returns None; an IndexError for a pair outside the points (nothing
 *   usable written). Runs without the GIL.
 * pairs_min(bound, first, second, z, add, backward_sign, base)
 *   The two np.minimum.at passes of a slope bound over the pairs, in place on bound (n,) float64: first, for each
 *   pair in order whose second point is in base (n,) bool (every pair when base is empty), bound[first] =
 *   minimum(bound[first], z[second] + add[p]); then, for each pair whose first point is in base, bound[second] =
 *   minimum(bound[second], z[first] + backward_sign * add[p]), as np.minimum (NaN propagates, the earlier value on
 *   a tie). Returns None; an IndexError for a pair outside the points (bound then partly updated). No GIL.
 * pairs_count(first, second, mask, out)
 *   out (n,) int64: how many pairs with both points in mask (n,) bool each point is in. Returns None; an
 *   IndexError for a pair outside the points. Runs without the GIL.
 *
 * lowest_in_cells(keys, z, cell_of, lowest) -> k
 *   The cells of points keyed by keys (n,) int64 (a cell's number, 0 <= key < 2^31) with heights z (n,) float64,
 *   as np.lexsort((z, keys)) orders them: the k distinct keys ascending; cell_of (n,) int64 each point's cell
 *   among them; lowest (n,) int64, its first k the point of least height in each cell (the first of equal ones).
 *   Returns k, or -1 (nothing usable written) for a key out of that range or a NaN height: the caller then sorts
 *   with NumPy. A radix sort of the keys, stable. Runs without the GIL.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "radix_sort.h"

/* np.clip's float loop: Min(Max(v, low), high), each keeping a NaN first operand. As selects, which the compiler
   makes without branches (a branch per cell mispredicts where cells reach the bounds). */
static inline float clip(float v, float low, float high) {
    const float raised = v > low ? v : low;
    v = isnan(v) ? v : raised;
    const float lowered = v < high ? v : high;
    return isnan(v) ? v : lowered;
}

static int update(float *log_odds, uint8_t *observed, Py_ssize_t width, Py_ssize_t x0, Py_ssize_t y0,
                  Py_ssize_t size, const float *ranges, const int32_t *bins, const float *free_range,
                  uint32_t bin_count, const uint8_t *hit, float hit_value, float miss_value, float low, float high) {
    float *reach = malloc(sizeof(float) * (size_t)size); /* a row's free ranges */
    if (reach == NULL) return -2;
    for (Py_ssize_t r = 0; r < size; ++r) {
        float *row = log_odds + (y0 + r) * width + x0;
        uint8_t *seen = observed + (y0 + r) * width + x0;
        const Py_ssize_t at = r * size;
        /* The row's lookups first, each bin checked on the way (none outside free_range is read): the pass over
           the row below then has no gather, and the compiler vectorises it. */
        int bad = 0;
        for (Py_ssize_t c = 0; c < size; ++c) {
            const int32_t bin = bins[at + c];
            const int outside = (uint32_t)bin >= bin_count; /* (negative ones too) */
            bad |= outside;
            reach[c] = free_range[outside ? 0 : bin];
        }
        if (bad) {
            free(reach);
            return -1;
        }
        for (Py_ssize_t c = 0; c < size; ++c) {
            const int is_hit = hit[at + c] != 0;
            const int is_free = ranges[at + c] < reach[c];
            /* (+ 0.0f also where neither: as NumPy adds it, turning a -0.0 into +0.0) */
            const float change = is_hit ? hit_value : (is_free ? miss_value : 0.0f);
            row[c] = clip(row[c] + change, low, high);
            seen[c] = (uint8_t)((seen[c] != 0) | is_hit | is_free);
        }
    }
    free(reach);
    return 0;
}

static PyObject *py_update_disk(PyObject *self, PyObject *args) {
    Py_buffer log_odds, observed, ranges, bins, free_range, hit;
    Py_ssize_t width, x0, y0, size;
    float hit_value, miss_value, low, high;
    (void)self;
    if (!PyArg_ParseTuple(args, "w*w*nnnny*y*y*y*ffff", &log_odds, &observed, &width, &x0, &y0, &size, &ranges,
                          &bins, &free_range, &hit, &hit_value, &miss_value, &low, &high)) {
        return NULL;
    }
    PyObject *result = NULL;
    const Py_ssize_t cells = observed.len;
    const Py_ssize_t height = width > 0 ? cells / width : 0;
    const Py_ssize_t disk = size * size;
    if (width < 1 || size < 1 || log_odds.len != cells * (Py_ssize_t)sizeof(float) || cells != height * width ||
        ranges.len != disk * (Py_ssize_t)sizeof(float) || bins.len != disk * (Py_ssize_t)sizeof(int32_t) ||
        hit.len != disk || free_range.len % (Py_ssize_t)sizeof(float) != 0 || free_range.len == 0) {
        PyErr_SetString(PyExc_ValueError, "update_disk: inconsistent buffer sizes");
        goto done;
    }
    if (x0 < 0 || y0 < 0 || x0 > width - size || y0 > height - size) {
        PyErr_SetString(PyExc_ValueError, "update_disk: the window lies outside the arrays");
        goto done;
    }
    /* (an int32 bin indexes 2^31 entries at most: the count fits 32 bits) */
    const Py_ssize_t entries = free_range.len / (Py_ssize_t)sizeof(float);
    const uint32_t bin_count = entries < ((Py_ssize_t)1 << 31) ? (uint32_t)entries : (uint32_t)1 << 31;
    int code;
    Py_BEGIN_ALLOW_THREADS
    code = update((float *)log_odds.buf, (uint8_t *)observed.buf, width, x0, y0, size, (const float *)ranges.buf,
                  (const int32_t *)bins.buf, (const float *)free_range.buf, bin_count, (const uint8_t *)hit.buf,
                  hit_value, miss_value, low, high);
    Py_END_ALLOW_THREADS
    if (code == -2) {
        PyErr_NoMemory();
        goto done;
    }
    if (code != 0) {
        PyErr_SetString(PyExc_IndexError, "update_disk: a bin is outside free_range");
        goto done;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&log_odds);
    PyBuffer_Release(&observed);
    PyBuffer_Release(&ranges);
    PyBuffer_Release(&bins);
    PyBuffer_Release(&free_range);
    PyBuffer_Release(&hit);
    return result;
}

static int cone(const double *grid, int64_t rows, int64_t columns, const int64_t *di, const int64_t *dj,
                const double *terms, Py_ssize_t m, const int64_t *cells, Py_ssize_t k, double *out) {
    for (Py_ssize_t q = 0; q < k; ++q) {
        const int64_t a = cells[2 * q], b = cells[2 * q + 1];
        if (a < 0 || a >= rows || b < 0 || b >= columns) return -1;
        double bound = INFINITY;
        for (Py_ssize_t t = 0; t < m; ++t) {
            const int64_t i = a - di[t], j = b - dj[t];
            if (i < 0 || i >= rows || j < 0 || j >= columns) continue;
            const double v = grid[i * columns + j] + terms[t];
            /* np.minimum(bound, v): NaN propagates (the first met stays), the earlier value on a tie */
            bound = (isnan(bound) | (bound <= v)) ? bound : v;
        }
        out[q] = bound;
    }
    return 0;
}

static PyObject *py_coarse_cone(PyObject *self, PyObject *args) {
    Py_buffer grid, di, dj, terms, cells, out;
    Py_ssize_t columns;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*ny*y*y*y*w*", &grid, &columns, &di, &dj, &terms, &cells, &out)) {
        return NULL;
    }
    PyObject *result = NULL;
    const Py_ssize_t row_bytes = columns * (Py_ssize_t)sizeof(double);
    const Py_ssize_t m = terms.len / (Py_ssize_t)sizeof(double);
    const Py_ssize_t k = out.len / (Py_ssize_t)sizeof(double);
    if (columns < 1 || grid.len % row_bytes != 0 || terms.len != m * (Py_ssize_t)sizeof(double) ||
        di.len != m * (Py_ssize_t)sizeof(int64_t) || dj.len != di.len || out.len != k * (Py_ssize_t)sizeof(double) ||
        cells.len != k * 2 * (Py_ssize_t)sizeof(int64_t)) {
        PyErr_SetString(PyExc_ValueError, "coarse_cone: inconsistent buffer sizes");
        goto done;
    }
    int code;
    Py_BEGIN_ALLOW_THREADS
    code = cone((const double *)grid.buf, grid.len / row_bytes, columns, (const int64_t *)di.buf,
                (const int64_t *)dj.buf, (const double *)terms.buf, m, (const int64_t *)cells.buf, k,
                (double *)out.buf);
    Py_END_ALLOW_THREADS
    if (code != 0) {
        PyErr_SetString(PyExc_IndexError, "coarse_cone: a cell is outside the grid");
        goto done;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&grid);
    PyBuffer_Release(&di);
    PyBuffer_Release(&dj);
    PyBuffer_Release(&terms);
    PyBuffer_Release(&cells);
    PyBuffer_Release(&out);
    return result;
}

/* ---- the pairs of points within a radius (occupancy_ground._Neighbours) ---- */

static int pairs_inside(const int64_t *first, const int64_t *second, Py_ssize_t m, Py_ssize_t n) {
    for (Py_ssize_t p = 0; p < m; ++p) {
        if (first[p] < 0 || first[p] >= n || second[p] < 0 || second[p] >= n) return 0;
    }
    return 1;
}

static PyObject *py_pair_offsets(PyObject *self, PyObject *args) {
    Py_buffer x, y, first, second, offsets, distance;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*y*y*w*w*", &x, &y, &first, &second, &offsets, &distance)) return NULL;
    PyObject *result = NULL;
    const Py_ssize_t n = x.len / (Py_ssize_t)sizeof(double), m = first.len / (Py_ssize_t)sizeof(int64_t);
    if (x.len != n * (Py_ssize_t)sizeof(double) || y.len != x.len || first.len != m * (Py_ssize_t)sizeof(int64_t) ||
        second.len != first.len || offsets.len != 2 * m * (Py_ssize_t)sizeof(double) ||
        distance.len != m * (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, "pair_offsets: inconsistent buffer sizes");
        goto done;
    }
    const double *px = x.buf, *py = y.buf;
    const int64_t *f = first.buf, *s = second.buf;
    double *o = offsets.buf, *d = distance.buf;
    int inside;
    Py_BEGIN_ALLOW_THREADS
    inside = pairs_inside(f, s, m, n);
    if (inside) {
        for (Py_ssize_t p = 0; p < m; ++p) {
            const double dx = px[f[p]] - px[s[p]], dy = py[f[p]] - py[s[p]];
            o[2 * p] = dx;
            o[2 * p + 1] = dy;
            d[p] = hypot(dx, dy);
        }
    }
    Py_END_ALLOW_THREADS
    if (!inside) {
        PyErr_SetString(PyExc_IndexError, "pair_offsets: a pair is outside the points");
        goto done;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&x);
    PyBuffer_Release(&y);
    PyBuffer_Release(&first);
    PyBuffer_Release(&second);
    PyBuffer_Release(&offsets);
    PyBuffer_Release(&distance);
    return result;
}

/* np.minimum(bound, v): NaN propagates (the first met stays), the earlier value on a tie */
static inline double minimum(double bound, double v) { return (isnan(bound) | (bound <= v)) ? bound : v; }

static PyObject *py_pairs_min(PyObject *self, PyObject *args) {
    Py_buffer bound, first, second, z, add, base;
    double backward_sign;
    (void)self;
    if (!PyArg_ParseTuple(args, "w*y*y*y*y*dy*", &bound, &first, &second, &z, &add, &backward_sign, &base)) {
        return NULL;
    }
    PyObject *result = NULL;
    const Py_ssize_t n = bound.len / (Py_ssize_t)sizeof(double), m = first.len / (Py_ssize_t)sizeof(int64_t);
    if (bound.len != n * (Py_ssize_t)sizeof(double) || z.len != bound.len ||
        first.len != m * (Py_ssize_t)sizeof(int64_t) || second.len != first.len ||
        add.len != m * (Py_ssize_t)sizeof(double) || (base.len != 0 && base.len != n)) {
        PyErr_SetString(PyExc_ValueError, "pairs_min: inconsistent buffer sizes");
        goto done;
    }
    double *b = bound.buf;
    const double *zz = z.buf, *a = add.buf;
    const int64_t *f = first.buf, *s = second.buf;
    const uint8_t *in = base.len ? (const uint8_t *)base.buf : NULL;
    int inside;
    Py_BEGIN_ALLOW_THREADS
    inside = pairs_inside(f, s, m, n);
    if (inside) {
        for (Py_ssize_t p = 0; p < m; ++p) {
            if (in == NULL || in[s[p]]) b[f[p]] = minimum(b[f[p]], zz[s[p]] + a[p]);
        }
        for (Py_ssize_t p = 0; p < m; ++p) {
            if (in == NULL || in[f[p]]) b[s[p]] = minimum(b[s[p]], zz[f[p]] + backward_sign * a[p]);
        }
    }
    Py_END_ALLOW_THREADS
    if (!inside) {
        PyErr_SetString(PyExc_IndexError, "pairs_min: a pair is outside the points");
        goto done;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&bound);
    PyBuffer_Release(&first);
    PyBuffer_Release(&second);
    PyBuffer_Release(&z);
    PyBuffer_Release(&add);
    PyBuffer_Release(&base);
    return result;
}

static PyObject *py_pairs_count(PyObject *self, PyObject *args) {
    Py_buffer first, second, mask, out;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*y*w*", &first, &second, &mask, &out)) return NULL;
    PyObject *result = NULL;
    const Py_ssize_t n = mask.len, m = first.len / (Py_ssize_t)sizeof(int64_t);
    if (first.len != m * (Py_ssize_t)sizeof(int64_t) || second.len != first.len ||
        out.len != n * (Py_ssize_t)sizeof(int64_t)) {
        PyErr_SetString(PyExc_ValueError, "pairs_count: inconsistent buffer sizes");
        goto done;
    }
    const int64_t *f = first.buf, *s = second.buf;
    const uint8_t *in = mask.buf;
    int64_t *count = out.buf;
    int inside;
    Py_BEGIN_ALLOW_THREADS
    inside = pairs_inside(f, s, m, n);
    if (inside) {
        for (Py_ssize_t i = 0; i < n; ++i) count[i] = 0;
        for (Py_ssize_t p = 0; p < m; ++p) {
            if (in[f[p]] && in[s[p]]) {
                count[f[p]] += 1;
                count[s[p]] += 1;
            }
        }
    }
    Py_END_ALLOW_THREADS
    if (!inside) {
        PyErr_SetString(PyExc_IndexError, "pairs_count: a pair is outside the points");
        goto done;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&first);
    PyBuffer_Release(&second);
    PyBuffer_Release(&mask);
    PyBuffer_Release(&out);
    return result;
}

static Py_ssize_t lowest_in_cells(const int64_t *keys, const double *z, Py_ssize_t n, int64_t *cell_of,
                                  int64_t *lowest) {
    int64_t largest = 0;
    for (Py_ssize_t i = 0; i < n; ++i) {
        if (keys[i] < 0 || keys[i] >= ((int64_t)1 << 31) || isnan(z[i])) return -1;
        if (keys[i] > largest) largest = keys[i];
    }
    uint64_t *a = malloc(sizeof(uint64_t) * (size_t)(n > 0 ? n : 1)), *b = malloc(sizeof(uint64_t) * (size_t)(n > 0 ? n : 1));
    if (a == NULL || b == NULL) {
        free(a);
        free(b);
        return -2;
    }
    for (Py_ssize_t i = 0; i < n; ++i) a[i] = ((uint64_t)keys[i] << 32) | (uint64_t)i;
    int bits = 0;
    while (bits < 31 && ((int64_t)1 << bits) <= largest) ++bits;
    const uint64_t *sorted = radix_sort_bits(a, b, n, 32, 32 + bits);
    Py_ssize_t k = 0;
    for (Py_ssize_t r = 0; r < n;) {
        const uint64_t key = sorted[r] >> 32;
        int64_t best = (int64_t)(sorted[r] & 0xffffffffu);
        Py_ssize_t e = r;
        for (; e < n && sorted[e] >> 32 == key; ++e) {
            const int64_t row = (int64_t)(sorted[e] & 0xffffffffu);
            cell_of[row] = k;
            if (z[row] < z[best]) best = row; /* (rows ascend within a cell: the first of equal heights stays) */
        }
        lowest[k++] = best;
        r = e;
    }
    free(a);
    free(b);
    return k;
}

static PyObject *py_lowest_in_cells(PyObject *self, PyObject *args) {
    Py_buffer keys, z, cell_of, lowest;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*w*w*", &keys, &z, &cell_of, &lowest)) return NULL;
    PyObject *result = NULL;
    const Py_ssize_t n = keys.len / (Py_ssize_t)sizeof(int64_t);
    if (keys.len != n * (Py_ssize_t)sizeof(int64_t) || z.len != n * (Py_ssize_t)sizeof(double) ||
        cell_of.len != keys.len || lowest.len != keys.len || n >= ((Py_ssize_t)1 << 32)) {
        PyErr_SetString(PyExc_ValueError, "lowest_in_cells: inconsistent buffer sizes");
        goto done;
    }
    Py_ssize_t k;
    Py_BEGIN_ALLOW_THREADS
    k = lowest_in_cells(keys.buf, z.buf, n, cell_of.buf, lowest.buf);
    Py_END_ALLOW_THREADS
    if (k == -2) {
        PyErr_NoMemory();
        goto done;
    }
    result = PyLong_FromSsize_t(k);
done:
    PyBuffer_Release(&keys);
    PyBuffer_Release(&z);
    PyBuffer_Release(&cell_of);
    PyBuffer_Release(&lowest);
    return result;
}

static PyMethodDef methods[] = {
    {"update_disk", py_update_disk, METH_VARARGS, "One keyframe's hits and misses into the grid (see the file)."},
    {"coarse_cone", py_coarse_cone, METH_VARARGS, "The slope cone's bound over a grid of cells (see the file)."},
    {"pair_offsets", py_pair_offsets, METH_VARARGS, "Offsets and distances of pairs of points (see the file)."},
    {"pairs_min", py_pairs_min, METH_VARARGS, "A slope bound's minima over pairs of points (see the file)."},
    {"pairs_count", py_pairs_count, METH_VARARGS, "Pairs within a mask, per point (see the file)."},
    {"lowest_in_cells", py_lowest_in_cells, METH_VARARGS, "Cells of keyed points and their lowest (see the file)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_occupancy_kernels", NULL, -1, methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__occupancy_kernels(void) { return PyModule_Create(&module); }
