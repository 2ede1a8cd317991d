/*
 * The plane fits of core/geometry.py (scan-to-map and scan-to-scan registration) in one pass over the
 * neighbourhoods, in C. geometry.fit_planes_at keeps its NumPy version as the fallback when this extension is not
 * built, and tests/test_geometry.py compares the two bit for bit.
 *
 * plane_fits(points, columns, index, k, max_residual, normals, offsets, moments, status)
 *   points (n, columns >= 3) float32, C-contiguous; index (m, k) int64, every value in [0, n): the neighbours of
 *   m neighbourhoods. For each, with its points taken as float64 (exactly), the operations of geometry.fit_planes
 *   in NumPy's order on x86-64 (built with -ffp-contract=off): the raw second moments summed from 0 in neighbour
 *   order (np.einsum over a strided axis), the coordinate sums from the first neighbour on (np.sum over axis 1),
 *   the cofactors and determinant of the normal equations, the normal solved and scaled to unit length (its
 *   squared norm summed as (x² + y²) + z², np.linalg.norm), the offset 1 / norm. Writes normals (m, 3) and
 *   offsets (m,) float64, moments (m, 9) float64 (xx, yy, zz, xy, xz, yz, then the three coordinate sums) and
 *   status (m,) uint8: 0 when the system is singular (|det| <= 1e-12) or a neighbour lies farther than
 *   max_residual [m] from the plane, 1 when every neighbour lies within it, 2 when a neighbour's distance is
 *   within 1e-9 m of max_residual: NumPy's einsum sums the three products of that distance in an order of its
 *   SIMD build, so the caller decides those few with NumPy itself. Returns None; raises IndexError for an index
 *   out of range (nothing usable written). Runs without the GIL.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>

#define UNDECIDED_M 1e-9 /* a residual this close to the bound [m] is decided by the caller */

static int fit(const float *points, Py_ssize_t columns, Py_ssize_t n, const int64_t *index, Py_ssize_t m,
               Py_ssize_t k, double max_residual, double *normals, double *offsets, double *moments,
               uint8_t *status) {
    for (Py_ssize_t row = 0; row < m; ++row) {
        const int64_t *neighbours = index + row * k;
        for (Py_ssize_t j = 0; j < k; ++j) {
            if (neighbours[j] < 0 || neighbours[j] >= n) return -1;
        }
        double xx = 0.0, yy = 0.0, zz = 0.0, xy = 0.0, xz = 0.0, yz = 0.0;
        double sx = 0.0, sy = 0.0, sz = 0.0;
        for (Py_ssize_t j = 0; j < k; ++j) {
            const float *p = points + neighbours[j] * columns;
            const double x = (double)p[0], y = (double)p[1], z = (double)p[2];
            xx += x * x;
            yy += y * y;
            zz += z * z;
            xy += x * y;
            xz += x * z;
            yz += y * z;
            if (j == 0) {
                sx = x;
                sy = y;
                sz = z;
            } else {
                sx += x;
                sy += y;
                sz += z;
            }
        }
        double *moment = moments + row * 9;
        moment[0] = xx;
        moment[1] = yy;
        moment[2] = zz;
        moment[3] = xy;
        moment[4] = xz;
        moment[5] = yz;
        moment[6] = sx;
        moment[7] = sy;
        moment[8] = sz;
        const double b0 = -sx, b1 = -sy, b2 = -sz;
        const double c00 = yy * zz - yz * yz, c01 = xz * yz - xy * zz, c02 = xy * yz - xz * yy;
        const double c11 = xx * zz - xz * xz, c12 = xy * xz - xx * yz, c22 = xx * yy - xy * xy;
        const double det = xx * c00 + xy * c01 + xz * c02;
        double *normal = normals + row * 3;
        if (!(fabs(det) > 1e-12)) {
            normal[0] = normal[1] = normal[2] = offsets[row] = NAN;
            status[row] = 0;
            continue;
        }
        double n0 = (c00 * b0 + c01 * b1 + c02 * b2) / det;
        double n1 = (c01 * b0 + c11 * b1 + c12 * b2) / det;
        double n2 = (c02 * b0 + c12 * b1 + c22 * b2) / det;
        const double norm = sqrt(n0 * n0 + n1 * n1 + n2 * n2);
        n0 /= norm;
        n1 /= norm;
        n2 /= norm;
        const double offset = 1.0 / norm;
        normal[0] = n0;
        normal[1] = n1;
        normal[2] = n2;
        offsets[row] = offset;
        uint8_t decided = 1;
        for (Py_ssize_t j = 0; j < k && decided; ++j) {
            const float *p = points + neighbours[j] * columns;
            /* NumPy's baseline SSE2 einsum: lanes (x n0 + z n2, y n1), then their sum */
            const double along = ((0.0 + (double)p[0] * n0) + (double)p[2] * n2) + (0.0 + (double)p[1] * n1);
            const double residual = fabs(along + offset);
            if (!(residual <= max_residual + UNDECIDED_M)) {
                decided = 0; /* beyond (or NaN): not a plane, whatever the order */
            } else if (residual >= max_residual - UNDECIDED_M) {
                decided = 2; /* too close to call here */
            }
        }
        status[row] = decided;
    }
    return 0;
}

static PyObject *py_plane_fits(PyObject *self, PyObject *args) {
    Py_buffer points, index, normals, offsets, moments, status;
    Py_ssize_t columns, k;
    double max_residual;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*ny*ndw*w*w*w*", &points, &columns, &index, &k, &max_residual, &normals, &offsets,
                          &moments, &status)) {
        return NULL;
    }
    PyObject *result = NULL;
    const Py_ssize_t row_bytes = columns * (Py_ssize_t)sizeof(float);
    if (columns < 3 || k < 1 || points.len % row_bytes != 0 || index.len % (k * (Py_ssize_t)sizeof(int64_t)) != 0) {
        PyErr_SetString(PyExc_ValueError, "plane_fits: points must be (n, columns >= 3) float32, index (m, k) int64");
        goto done;
    }
    const Py_ssize_t n = points.len / row_bytes;
    const Py_ssize_t m = index.len / (k * (Py_ssize_t)sizeof(int64_t));
    if (normals.len != m * 3 * (Py_ssize_t)sizeof(double) || offsets.len != m * (Py_ssize_t)sizeof(double) ||
        moments.len != m * 9 * (Py_ssize_t)sizeof(double) || status.len != m) {
        PyErr_SetString(PyExc_ValueError, "plane_fits: outputs must be (m, 3), (m,), (m, 9) float64 and (m,) uint8");
        goto done;
    }
    int code;
    Py_BEGIN_ALLOW_THREADS
    code = fit((const float *)points.buf, columns, n, (const int64_t *)index.buf, m, k, max_residual,
               (double *)normals.buf, (double *)offsets.buf, (double *)moments.buf, (uint8_t *)status.buf);
    Py_END_ALLOW_THREADS
    if (code != 0) {
        PyErr_SetString(PyExc_IndexError, "plane_fits: a neighbour index is out of range");
        goto done;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&points);
    PyBuffer_Release(&index);
    PyBuffer_Release(&normals);
    PyBuffer_Release(&offsets);
    PyBuffer_Release(&moments);
    PyBuffer_Release(&status);
    return result;
}

static PyMethodDef methods[] = {
    {"plane_fits", py_plane_fits, METH_VARARGS, "Least-squares planes through neighbourhoods (see the file)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_geometry_kernels", NULL, -1, methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__geometry_kernels(void) { return PyModule_Create(&module); }
