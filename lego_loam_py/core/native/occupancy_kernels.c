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
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

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

static PyMethodDef methods[] = {
    {"update_disk", py_update_disk, METH_VARARGS, "One keyframe's hits and misses into the grid (see the file)."},
    {"coarse_cone", py_coarse_cone, METH_VARARGS, "The slope cone's bound over a grid of cells (see the file)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_occupancy_kernels", NULL, -1, methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__occupancy_kernels(void) { return PyModule_Create(&module); }
