/*
 * The greedy part of LeGO-LOAM's feature extraction, which is sequential by nature: in each sub-region the
 * candidates are visited in curvature order and every pick suppresses its neighbours for the picks after it.
 * lego_loam_py/core/features.py prepares everything vectorised (candidate order, per-region bounds, the slice
 * each pick marks) and calls select() here; without this extension it runs the same loop in Python.
 *
 *   select(edges, edge_bounds, edge_start, edge_stop, flats, flat_bounds, flat_start, flat_stop, taken,
 *          edge_num, less_edge_num, surf_num, sharp, less_sharp, less_sharp_region, flat)
 *     -> (number of sharp, less sharp, flat)
 *
 * Index arrays are contiguous int64; *_bounds hold regions + 1 entries (region r: [bounds[r], bounds[r + 1]));
 * taken is a writable uint8 array of the n points (1: picked or suppressed); the four outputs are int64
 * arrays large enough for regions x the per-region limits. A negative candidate index reads point index + n,
 * as Python indexing does; the slices [start, stop) are already within [0, n].
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#define N_BUFFERS 13

/* taken[start:stop] = 1, within the array whatever the slice says. */
static inline void mark(uint8_t *taken, Py_ssize_t n, int64_t start, int64_t stop) {
    if (start < 0) start = 0;
    if (stop > n) stop = n;
    if (stop > start) memset(taken + start, 1, (size_t)(stop - start));
}

static PyObject *py_select(PyObject *self, PyObject *args) {
    Py_buffer b[N_BUFFERS];
    long long edge_num, less_edge_num, surf_num;
    memset(b, 0, sizeof(b));
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*y*y*w*LLLw*w*w*w*", &b[0], &b[1], &b[2], &b[3], &b[4], &b[5], &b[6],
                          &b[7], &b[8], &edge_num, &less_edge_num, &surf_num, &b[9], &b[10], &b[11], &b[12])) {
        return NULL;
    }
    PyObject *result = NULL;
    const int64_t *edges = b[0].buf, *edge_bounds = b[1].buf, *edge_start = b[2].buf, *edge_stop = b[3].buf;
    const int64_t *flats = b[4].buf, *flat_bounds = b[5].buf, *flat_start = b[6].buf, *flat_stop = b[7].buf;
    uint8_t *taken = b[8].buf;
    int64_t *sharp = b[9].buf, *less_sharp = b[10].buf, *less_region = b[11].buf, *flat = b[12].buf;
    Py_ssize_t n = b[8].len;
    Py_ssize_t regions = b[1].len / 8 - 1;
    Py_ssize_t n_edges = b[0].len / 8, n_flats = b[4].len / 8;
    if (regions < 0 || b[5].len != b[1].len || b[2].len != b[0].len || b[3].len != b[0].len ||
        b[6].len != b[4].len || b[7].len != b[4].len || edge_bounds[regions] > n_edges ||
        flat_bounds[regions] > n_flats || b[9].len / 8 < regions * edge_num ||
        b[10].len / 8 < regions * less_edge_num || b[11].len != b[10].len || b[12].len / 8 < regions * surf_num) {
        PyErr_SetString(PyExc_ValueError, "select: inconsistent buffer sizes");
        goto done;
    }
    Py_ssize_t n_sharp = 0, n_less = 0, n_flat = 0;
    for (Py_ssize_t region = 0; region < regions; ++region) {
        long long count = 0;
        for (int64_t i = edge_bounds[region]; i < edge_bounds[region + 1]; ++i) {
            int64_t k = edges[i] < 0 ? edges[i] + n : edges[i];
            if (k < 0 || k >= n || taken[k]) {
                continue;
            }
            ++count;
            if (count <= edge_num) {
                sharp[n_sharp++] = edges[i];
            } else if (count > less_edge_num) {
                break;
            }
            less_sharp[n_less] = edges[i];
            less_region[n_less++] = region;
            mark(taken, n, edge_start[i], edge_stop[i]);
        }
        count = 0;
        for (int64_t i = flat_bounds[region]; i < flat_bounds[region + 1]; ++i) {
            int64_t k = flats[i] < 0 ? flats[i] + n : flats[i];
            if (k < 0 || k >= n || taken[k]) {
                continue;
            }
            flat[n_flat++] = flats[i];
            if (++count >= surf_num) {
                break;
            }
            mark(taken, n, flat_start[i], flat_stop[i]);
        }
    }
    result = Py_BuildValue("nnn", n_sharp, n_less, n_flat);
done:
    for (int i = 0; i < N_BUFFERS; ++i) {
        if (b[i].obj != NULL) {
            PyBuffer_Release(&b[i]);
        }
    }
    return result;
}

static PyMethodDef methods[] = {
    {"select", py_select, METH_VARARGS, "The greedy edge and flat selection of every sub-region (see the file)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_feature_selection", NULL, -1, methods};

PyMODINIT_FUNC PyInit__feature_selection(void) { return PyModule_Create(&module); }
