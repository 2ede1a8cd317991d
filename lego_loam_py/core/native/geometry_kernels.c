/*
 * The plane fits of core/geometry.py (scan-to-map and scan-to-scan registration) in one pass over the
 * neighbourhoods, in C. geometry.fit_planes_at keeps its NumPy version as the fallback when this extension is not
 * built, and tests/test_geometry.py compares the two bit for bit. Also the scan-to-map registration's search for
 * neighbours, on a grid of cubic cells (geometry.GridNeighbours), with cKDTree's answers.
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
 *
 * line_fits(points, columns, index, k, eigen_ratio, centroids, directions, status)
 *   points and index as for plane_fits. For each neighbourhood, with its points taken as float64: the centroid (the
 *   coordinates summed neighbour by neighbour, divided by k, as NumPy's mean over axis 1), the covariance of the
 *   centred points (divided by k) and its eigen decomposition (symmetric_eigen.h; LAPACK's to rounding, not bit for
 *   bit). Writes centroids (m, 3) and directions (m, 3) float64 (the unit eigenvector of the largest eigenvalue;
 *   its sign is arbitrary) and status (m,) uint8: 1 when the largest eigenvalue exceeds eigen_ratio times the
 *   middle one (the neighbours lie along a line), else 0. Returns None; raises IndexError for an index out of
 *   range. Runs without the GIL.
 * map_plane_terms(points, columns, used, normals, offsets, weight_gain, min_weight, kept, coefficients) -> count
 *   scan_to_map.plane_correspondences after its plane fits, NumPy's operations in its order: for the points
 *   used (j,) int64 rows of points (n, columns >= 3) float32 and their planes (normals (j, 3), offsets (j,)
 *   float64), the signed distance (the point's float64 coordinates dotted with the normal as NumPy's einsum sums
 *   three products, plus the offset), the weight 1 - weight_gain |distance| / sqrt(|p|) (|p| = sqrt((x² + y²) +
 *   z²)), kept when above min_weight: their rows written to kept (j,) int64 and (normal * weight, weight *
 *   distance) to coefficients (j, 4) float64, in order. Returns how many were kept. Runs without the GIL.
 * map_line_terms(points, columns, used, centroids, directions, half_length, weight_gain, min_weight, kept,
 *                coefficients) -> count
 *   scan_to_map.edge_correspondences after its line fits: the line ends a, b = centroid +- half_length *
 *   direction (float64, then float32) and geometry.line_coefficients in float32 (the cross product of p - a and
 *   p - b, its norm and that of a - b summed (x² + y²) + z²), the weight 1 - weight_gain |distance|, kept when
 *   above min_weight with a finite distance and gradient: rows to kept, (gradient * weight, weight * distance)
 *   to coefficients (j, 4) float64. Returns how many were kept. Runs without the GIL.
 * grid_extent(points, columns, cell) -> ((i0, j0, k0), (i1, j1, k1)) or None
 *   The lowest and highest cubic cell of side `cell` [m] of the points (n, columns >= 3) float32, a cell being
 *   floor(coordinate / cell) per axis in float64; None when a coordinate is not finite or absurdly far.
 * grid_fill(points, columns, cell, low, size, starts, sorted_xyz, sorted_rows, cell_of)
 *   Sorts the points by cell (counting sort, stable) over the cells from `low` (i0, j0, k0) of `size` (ni, nj, nk),
 *   numbered ((i * nj) + j) * nk + k: starts (cells + 1,) int32, sorted_xyz (n, 3) float64 (the coordinates,
 *   exactly), sorted_rows (n,) int64 (each one's row); cell_of (n,) int64 is scratch.
 * grid_nearest(cell, low, size, starts, sorted_xyz, sorted_rows, queries, query_columns, k, search_sq, gate_sq,
 *              status, index)
 *   For each query (m, query_columns >= 3) float32 its k nearest points over the 27 cells around its own (a cell
 *   must span the search radius), by the squared distance cKDTree computes, ((dx^2 + dy^2) + dz^2) in float64.
 *   status (m,) uint8: 1 when k points lie within search_sq and the k-th one's distance, sqrt(d2), squared is below
 *   gate_sq (geometry.nearest_within's test), their rows in index (m, k) int64, nearest first; 0 otherwise; 2 when
 *   it would be 1 but two of the k + 1 nearest lie at exactly the same distance (an order cKDTree decides by its
 *   own walk: the caller asks it).
 * grid_nearest_one(cell, low, size, starts, sorted_xyz, sorted_rows, queries, query_columns, max_shell, gate_sq,
 *                  status, index)
 *   For each query its nearest point, searched shell by shell of cells around its own (shell s: the cells s away
 *   along some axis) until the nearest found is closer than s cells, up to max_shell (at least the gate's radius
 *   in cells): status 1 when its distance, sqrt(d2), squared is below gate_sq, its row in index (m,) int64; 0
 *   otherwise; 2 when two points lie at exactly that nearest distance (the caller asks cKDTree). All four run
 *   without the GIL.
 *
 * pairs_within(xy, radius, first, second) -> count
 *   The pairs of points of xy (n, 2) float64 within `radius` [m] of each other, as cKDTree.query_pairs decides
 *   (dx^2 + dy^2 <= radius^2), each once as (i, j) with i < j, ordered by i: written to first and second (int64,
 *   of equal capacity) up to their capacity. Returns the number of pairs (the caller calls again with room for
 *   all when it exceeds the capacity), or -1 for points the grid cannot hold (not finite, absurdly far, or more than
 *   2^24 cells of the radius across): the caller then asks cKDTree. Runs without the GIL.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "symmetric_eigen.h"

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

/* The n points (n, columns >= 3) float32 and the m neighbourhoods (m, k) int64 of plane_fits and line_fits: 1, or
 * 0 with a ValueError naming the function. */
static int neighbourhood_sizes(const Py_buffer *points, Py_ssize_t columns, const Py_buffer *index, Py_ssize_t k,
                               const char *function, Py_ssize_t *n, Py_ssize_t *m) {
    const Py_ssize_t row_bytes = columns * (Py_ssize_t)sizeof(float);
    if (columns < 3 || k < 1 || points->len % row_bytes != 0 || index->len % (k * (Py_ssize_t)sizeof(int64_t)) != 0) {
        PyErr_Format(PyExc_ValueError, "%s: points must be (n, columns >= 3) float32, index (m, k) int64", function);
        return 0;
    }
    *n = points->len / row_bytes;
    *m = index->len / (k * (Py_ssize_t)sizeof(int64_t));
    return 1;
}

/* What plane_fits and line_fits return: None, or an IndexError when a neighbour index was out of range. */
static PyObject *fitted(int code, const char *function) {
    if (code != 0) {
        PyErr_Format(PyExc_IndexError, "%s: a neighbour index is out of range", function);
        return NULL;
    }
    Py_RETURN_NONE;
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
    Py_ssize_t n, m;
    if (!neighbourhood_sizes(&points, columns, &index, k, "plane_fits", &n, &m)) goto done;
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
    result = fitted(code, "plane_fits");
done:
    PyBuffer_Release(&points);
    PyBuffer_Release(&index);
    PyBuffer_Release(&normals);
    PyBuffer_Release(&offsets);
    PyBuffer_Release(&moments);
    PyBuffer_Release(&status);
    return result;
}

static int line_fit(const float *points, Py_ssize_t columns, Py_ssize_t n, const int64_t *index, Py_ssize_t m,
                    Py_ssize_t k, double eigen_ratio, double *centroids, double *directions, uint8_t *status) {
    for (Py_ssize_t row = 0; row < m; ++row) {
        const int64_t *neighbours = index + row * k;
        for (Py_ssize_t j = 0; j < k; ++j) {
            if (neighbours[j] < 0 || neighbours[j] >= n) return -1;
        }
        double sx = 0.0, sy = 0.0, sz = 0.0;
        for (Py_ssize_t j = 0; j < k; ++j) {
            const float *p = points + neighbours[j] * columns;
            if (j == 0) {
                sx = (double)p[0];
                sy = (double)p[1];
                sz = (double)p[2];
            } else {
                sx += (double)p[0];
                sy += (double)p[1];
                sz += (double)p[2];
            }
        }
        const double cx = sx / (double)k, cy = sy / (double)k, cz = sz / (double)k;
        double covariance[9] = {0.0};
        for (Py_ssize_t j = 0; j < k; ++j) {
            const float *p = points + neighbours[j] * columns;
            const double dx = (double)p[0] - cx, dy = (double)p[1] - cy, dz = (double)p[2] - cz;
            covariance[0] += dx * dx;
            covariance[1] += dx * dy;
            covariance[2] += dx * dz;
            covariance[4] += dy * dy;
            covariance[5] += dy * dz;
            covariance[8] += dz * dz;
        }
        for (int i = 0; i < 9; ++i) covariance[i] /= (double)k;
        covariance[3] = covariance[1];
        covariance[6] = covariance[2];
        covariance[7] = covariance[5];
        double values[3], vectors[9];
        symmetric_eigen(covariance, values, vectors);
        double *centroid = centroids + row * 3, *direction = directions + row * 3;
        centroid[0] = cx;
        centroid[1] = cy;
        centroid[2] = cz;
        direction[0] = vectors[2];
        direction[1] = vectors[5];
        direction[2] = vectors[8];
        status[row] = values[2] > eigen_ratio * values[1];
    }
    return 0;
}

static PyObject *py_line_fits(PyObject *self, PyObject *args) {
    Py_buffer points, index, centroids, directions, status;
    Py_ssize_t columns, k;
    double eigen_ratio;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*ny*ndw*w*w*", &points, &columns, &index, &k, &eigen_ratio, &centroids,
                          &directions, &status)) {
        return NULL;
    }
    PyObject *result = NULL;
    Py_ssize_t n, m;
    if (!neighbourhood_sizes(&points, columns, &index, k, "line_fits", &n, &m)) goto done;
    if (centroids.len != m * 3 * (Py_ssize_t)sizeof(double) || directions.len != m * 3 * (Py_ssize_t)sizeof(double) ||
        status.len != m) {
        PyErr_SetString(PyExc_ValueError, "line_fits: outputs must be (m, 3), (m, 3) float64 and (m,) uint8");
        goto done;
    }
    int code;
    Py_BEGIN_ALLOW_THREADS
    code = line_fit((const float *)points.buf, columns, n, (const int64_t *)index.buf, m, k, eigen_ratio,
                    (double *)centroids.buf, (double *)directions.buf, (uint8_t *)status.buf);
    Py_END_ALLOW_THREADS
    result = fitted(code, "line_fits");
done:
    PyBuffer_Release(&points);
    PyBuffer_Release(&index);
    PyBuffer_Release(&centroids);
    PyBuffer_Release(&directions);
    PyBuffer_Release(&status);
    return result;
}

static Py_ssize_t map_plane_term(const float *points, Py_ssize_t columns, Py_ssize_t n, const int64_t *used,
                                 Py_ssize_t j, const double *normals, const double *offsets, double gain,
                                 double min_weight, int64_t *kept, double *coefficients) {
    Py_ssize_t count = 0;
    for (Py_ssize_t r = 0; r < j; ++r) {
        if (used[r] < 0 || used[r] >= n) return -1;
        const float *p = points + used[r] * columns;
        const double x = (double)p[0], y = (double)p[1], z = (double)p[2];
        const double *normal = normals + 3 * r;
        /* NumPy's baseline SSE2 einsum: lanes (x n0 + z n2, y n1), then their sum */
        const double distance = (((0.0 + x * normal[0]) + z * normal[2]) + (0.0 + y * normal[1])) + offsets[r];
        const double length = sqrt((x * x + y * y) + z * z);
        const double weight = 1.0 - gain * fabs(distance) / sqrt(length);
        if (!(weight > min_weight)) continue;
        kept[count] = used[r];
        double *row = coefficients + 4 * count;
        row[0] = normal[0] * weight;
        row[1] = normal[1] * weight;
        row[2] = normal[2] * weight;
        row[3] = weight * distance;
        ++count;
    }
    return count;
}

static Py_ssize_t map_line_term(const float *points, Py_ssize_t columns, Py_ssize_t n, const int64_t *used,
                                Py_ssize_t j, const double *centroids, const double *directions, double half_length,
                                double gain, double min_weight, int64_t *kept, double *coefficients) {
    Py_ssize_t count = 0;
    for (Py_ssize_t r = 0; r < j; ++r) {
        if (used[r] < 0 || used[r] >= n) return -1;
        const float *p = points + used[r] * columns;
        const double *c = centroids + 3 * r, *d = directions + 3 * r;
        float a[3], b[3], pa[3], pb[3], ab[3];
        for (int i = 0; i < 3; ++i) {
            a[i] = (float)(c[i] + half_length * d[i]);
            b[i] = (float)(c[i] - half_length * d[i]);
            pa[i] = p[i] - a[i];
            pb[i] = p[i] - b[i];
            ab[i] = a[i] - b[i];
        }
        const float cross[3] = {pa[1] * pb[2] - pa[2] * pb[1], pa[2] * pb[0] - pa[0] * pb[2],
                                pa[0] * pb[1] - pa[1] * pb[0]};
        const float area = sqrtf((cross[0] * cross[0] + cross[1] * cross[1]) + cross[2] * cross[2]);
        const float length = sqrtf((ab[0] * ab[0] + ab[1] * ab[1]) + ab[2] * ab[2]);
        const float scale = area * length;
        const float gradient[3] = {(ab[1] * cross[2] - ab[2] * cross[1]) / scale,
                                   (ab[2] * cross[0] - ab[0] * cross[2]) / scale,
                                   (ab[0] * cross[1] - ab[1] * cross[0]) / scale};
        const float distance = area / length;
        const double weight = 1.0 - gain * fabs((double)distance);
        if (!(weight > min_weight) || !isfinite(distance) || !isfinite(gradient[0]) || !isfinite(gradient[1]) ||
            !isfinite(gradient[2])) {
            continue;
        }
        kept[count] = used[r];
        double *row = coefficients + 4 * count;
        row[0] = (double)gradient[0] * weight;
        row[1] = (double)gradient[1] * weight;
        row[2] = (double)gradient[2] * weight;
        row[3] = weight * (double)distance;
        ++count;
    }
    return count;
}

/* The used rows j of map_plane_terms and map_line_terms from their buffers (points, used, the fits' two arrays of
 * 3 and second_columns per row, kept, coefficients): 1, or 0 with a ValueError naming the function. */
static int terms_rows(const Py_buffer *b, Py_ssize_t columns, Py_ssize_t second_columns, const char *function,
                      Py_ssize_t *j) {
    const Py_ssize_t row_bytes = columns * (Py_ssize_t)sizeof(float);
    *j = b[1].len / (Py_ssize_t)sizeof(int64_t);
    if (columns < 3 || b[0].len % row_bytes != 0 || b[1].len != *j * 8 || b[2].len != 3 * *j * 8 ||
        b[3].len != second_columns * *j * 8 || b[4].len != *j * 8 || b[5].len != 4 * *j * 8) {
        PyErr_Format(PyExc_ValueError, "%s: inconsistent buffer sizes", function);
        return 0;
    }
    return 1;
}

/* What map_plane_terms and map_line_terms return (the rows kept, or an IndexError for a row out of range), their
 * six buffers released. */
static PyObject *terms_result(Py_ssize_t count, Py_buffer *b, const char *function) {
    PyObject *result = NULL;
    if (count == -2) { /* (the buffers were refused: the error is set) */
    } else if (count < 0) {
        PyErr_Format(PyExc_IndexError, "%s: a row out of range", function);
    } else {
        result = PyLong_FromSsize_t(count);
    }
    for (int i = 0; i < 6; ++i) {
        if (b[i].obj != NULL) PyBuffer_Release(&b[i]);
    }
    return result;
}

static PyObject *py_map_plane_terms(PyObject *self, PyObject *args) {
    Py_buffer b[6];
    Py_ssize_t columns, j, count = -2;
    double gain, min_weight;
    (void)self;
    memset(b, 0, sizeof(b));
    if (!PyArg_ParseTuple(args, "y*ny*y*y*ddw*w*", &b[0], &columns, &b[1], &b[2], &b[3], &gain, &min_weight, &b[4],
                          &b[5])) {
        return NULL;
    }
    if (terms_rows(b, columns, 1, "map_plane_terms", &j)) {
        Py_BEGIN_ALLOW_THREADS
        count = map_plane_term(b[0].buf, columns, b[0].len / (columns * (Py_ssize_t)sizeof(float)), b[1].buf, j,
                               b[2].buf, b[3].buf, gain, min_weight, b[4].buf, b[5].buf);
        Py_END_ALLOW_THREADS
    }
    return terms_result(count, b, "map_plane_terms");
}

static PyObject *py_map_line_terms(PyObject *self, PyObject *args) {
    Py_buffer b[6];
    Py_ssize_t columns, j, count = -2;
    double half_length, gain, min_weight;
    (void)self;
    memset(b, 0, sizeof(b));
    if (!PyArg_ParseTuple(args, "y*ny*y*y*dddw*w*", &b[0], &columns, &b[1], &b[2], &b[3], &half_length, &gain,
                          &min_weight, &b[4], &b[5])) {
        return NULL;
    }
    if (terms_rows(b, columns, 3, "map_line_terms", &j)) {
        Py_BEGIN_ALLOW_THREADS
        count = map_line_term(b[0].buf, columns, b[0].len / (columns * (Py_ssize_t)sizeof(float)), b[1].buf, j,
                              b[2].buf, b[3].buf, half_length, gain, min_weight, b[4].buf, b[5].buf);
        Py_END_ALLOW_THREADS
    }
    return terms_result(count, b, "map_line_terms");
}

#define GRID_MAX_INDEX 1e15 /* cell indices beyond this (far points, NaN): no grid */
#define MAX_K 64

/* The grid: cells of side `cell` numbered ((i * nj) + j) * nk + k from the lowest cell (i0, j0, k0) of the points;
   the points sorted by cell, their float64 coordinates in sorted_xyz (3 per point) and their rows in sorted_rows;
   cell c holds sorted positions [starts[c], starts[c + 1]). */
typedef struct {
    double cell;
    int64_t i0, j0, k0, ni, nj, nk;
    const int32_t *starts;
    const double *sorted_xyz;
    const int64_t *sorted_rows;
} Grid;

static inline void cell_index(double x, double y, double z, double cell, double *out) {
    out[0] = floor(x / cell);
    out[1] = floor(y / cell);
    out[2] = floor(z / cell);
}

/* The lowest and highest cell of the points: 1, or 0 when a coordinate is not finite or the cells are absurd. */
static int extent(const float *points, Py_ssize_t columns, Py_ssize_t n, double cell, int64_t *low, int64_t *high) {
    double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (Py_ssize_t i = 0; i < n; ++i) {
        const float *p = points + i * columns;
        double c[3];
        cell_index((double)p[0], (double)p[1], (double)p[2], cell, c);
        for (int a = 0; a < 3; ++a) {
            if (!(fabs(c[a]) < GRID_MAX_INDEX)) return 0;
            if (c[a] < lo[a]) lo[a] = c[a];
            if (c[a] > hi[a]) hi[a] = c[a];
        }
    }
    for (int a = 0; a < 3; ++a) {
        low[a] = (int64_t)lo[a];
        high[a] = (int64_t)hi[a];
    }
    return 1;
}

static void fill(const float *points, Py_ssize_t columns, Py_ssize_t n, double cell, const int64_t *low,
                 const int64_t *size, int32_t *starts, double *sorted_xyz, int64_t *sorted_rows, int64_t *cell_of) {
    const int64_t cells = size[0] * size[1] * size[2];
    for (int64_t c = 0; c <= cells; ++c) starts[c] = 0;
    for (Py_ssize_t i = 0; i < n; ++i) {
        const float *p = points + i * columns;
        double c[3];
        cell_index((double)p[0], (double)p[1], (double)p[2], cell, c);
        const int64_t number =
            (((int64_t)c[0] - low[0]) * size[1] + ((int64_t)c[1] - low[1])) * size[2] + ((int64_t)c[2] - low[2]);
        cell_of[i] = number;
        starts[number + 1] += 1;
    }
    for (int64_t c = 0; c < cells; ++c) starts[c + 1] += starts[c];
    for (Py_ssize_t i = 0; i < n; ++i) { /* (starts[c] advances as cell c fills; shifted back below) */
        const int64_t at = starts[cell_of[i]]++;
        const float *p = points + i * columns;
        sorted_xyz[3 * at] = (double)p[0];
        sorted_xyz[3 * at + 1] = (double)p[1];
        sorted_xyz[3 * at + 2] = (double)p[2];
        sorted_rows[at] = (int64_t)i;
    }
    for (int64_t c = cells; c > 0; --c) starts[c] = starts[c - 1];
    starts[0] = 0;
}

/* The sorted positions [begin, end) of cells (i, j, k_low..k_high) of the grid, clipped to it; 0 when none. */
static inline int column_run(const Grid *grid, int64_t i, int64_t j, int64_t k_low, int64_t k_high, int64_t *begin,
                             int64_t *end) {
    if (i < 0 || i >= grid->ni || j < 0 || j >= grid->nj) return 0;
    if (k_low < 0) k_low = 0;
    if (k_high >= grid->nk) k_high = grid->nk - 1;
    if (k_low > k_high) return 0;
    const int64_t column = (i * grid->nj + j) * grid->nk;
    *begin = grid->starts[column + k_low];
    *end = grid->starts[column + k_high + 1];
    return *begin < *end;
}

/* The squared distance cKDTree computes, ((dx^2 + dy^2) + dz^2) in float64 (built without fused multiply-adds). */
static inline double squared_distance(const double *p, const double *q) {
    const double dx = p[0] - q[0], dy = p[1] - q[1], dz = p[2] - q[2];
    double d2 = dx * dx;
    d2 += dy * dy;
    d2 += dz * dz;
    return d2;
}

/* A query's coordinates (float64) and its cell relative to the grid's lowest; 0 when not finite or absurdly far. */
static inline int query_cell(const Grid *grid, const float *q, double *xyz, int64_t *ijk) {
    double c[3];
    xyz[0] = (double)q[0];
    xyz[1] = (double)q[1];
    xyz[2] = (double)q[2];
    cell_index(xyz[0], xyz[1], xyz[2], grid->cell, c);
    if (!(fabs(c[0]) < GRID_MAX_INDEX && fabs(c[1]) < GRID_MAX_INDEX && fabs(c[2]) < GRID_MAX_INDEX)) return 0;
    ijk[0] = (int64_t)c[0] - grid->i0;
    ijk[1] = (int64_t)c[1] - grid->j0;
    ijk[2] = (int64_t)c[2] - grid->k0;
    return 1;
}

/* The 3 x 3 columns of cells around a query's: its own first, then the 4 beside it and the 4 at its corners, so
   that the nearest points come early and most later ones are passed over at one comparison. */
static const int8_t COLUMNS[9][2] = {{0, 0}, {-1, 0}, {1, 0}, {0, -1}, {0, 1}, {-1, -1}, {-1, 1}, {1, -1}, {1, 1}};

/* Each query's k nearest points within the search radius (the cells span it, so the 3 x 3 x 3 cells around the
   query's hold them), ascending. The result does not depend on the order the cells are visited in: a point joins
   the k + 1 nearest so far only when strictly nearer than the last of them, and equal distances among the k + 1
   are reported (status 2) for the caller to settle. A column is passed over once k + 1 are found and its
   horizontal distance from the query (less a margin far above rounding: a point's cell comes from a rounded
   division) is no shorter than the (k + 1)-th. */
static void nearest(const Grid *grid, const float *queries, Py_ssize_t query_columns, Py_ssize_t m, Py_ssize_t k,
                    double search_sq, double gate_sq, uint8_t *status, int64_t *index) {
    double best[MAX_K + 1];
    int64_t which[MAX_K + 1];
    /* d2 <= search_sq as d2 < admit: one comparison admits a point while fewer than k + 1 are found */
    const double admit = nextafter(search_sq, INFINITY);
    const int64_t origin[2] = {grid->i0, grid->j0};
    for (Py_ssize_t row = 0; row < m; ++row) {
        double q[3];
        int64_t cell[3];
        status[row] = 0;
        if (!query_cell(grid, queries + row * query_columns, q, cell)) continue;
        double gap_sq[2][3]; /* [axis][offset + 1]: squared distance from the query to that column's side [m^2] */
        for (int a = 0; a < 2; ++a) {
            const double face = (double)(cell[a] + origin[a]) * grid->cell; /* the query's cell's lower side */
            const double margin = 1e-9 * (fabs(q[a]) + grid->cell);
            const double below = q[a] - face - margin, above = face + grid->cell - q[a] - margin;
            gap_sq[a][0] = below > 0.0 ? below * below : 0.0;
            gap_sq[a][1] = 0.0;
            gap_sq[a][2] = above > 0.0 ? above * above : 0.0;
        }
        Py_ssize_t found = 0; /* the k + 1 nearest so far, ascending */
        double bound = admit;  /* a point is taken when nearer than this */
        for (int c = 0; c < 9; ++c) {
            const int di = COLUMNS[c][0], dj = COLUMNS[c][1];
            if (found == k + 1 && (gap_sq[0][di + 1] + gap_sq[1][dj + 1]) * (1.0 - 1e-9) >= bound) continue;
            int64_t begin, end;
            if (!column_run(grid, cell[0] + di, cell[1] + dj, cell[2] - 1, cell[2] + 1, &begin, &end)) continue;
            for (int64_t at = begin; at < end; ++at) {
                const double d2 = squared_distance(grid->sorted_xyz + 3 * at, q);
                if (!(d2 < bound)) continue;
                Py_ssize_t slot = found < k + 1 ? found++ : k;
                while (slot > 0 && best[slot - 1] > d2) {
                    best[slot] = best[slot - 1];
                    which[slot] = which[slot - 1];
                    --slot;
                }
                best[slot] = d2;
                which[slot] = grid->sorted_rows[at];
                if (found == k + 1) bound = best[k];
            }
        }
        if (found < k) continue;
        const double kth = sqrt(best[k - 1]);
        if (!(kth * kth < gate_sq)) continue;
        uint8_t decided = 1;
        for (Py_ssize_t j = 0; j + 1 < found; ++j) {
            if (best[j] == best[j + 1]) decided = 2;
        }
        status[row] = decided;
        for (Py_ssize_t j = 0; j < k; ++j) index[row * k + j] = which[j];
    }
}

static PyObject *py_grid_extent(PyObject *self, PyObject *args) {
    Py_buffer points;
    Py_ssize_t columns;
    double cell;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*nd", &points, &columns, &cell)) return NULL;
    PyObject *result = NULL;
    if (columns < 3 || points.len % (columns * (Py_ssize_t)sizeof(float)) != 0 || !(cell > 0.0)) {
        PyErr_SetString(PyExc_ValueError, "grid_extent: points must be (n, columns >= 3) float32, cell > 0");
        goto done;
    }
    const Py_ssize_t n = points.len / (columns * (Py_ssize_t)sizeof(float));
    int64_t low[3] = {0, 0, 0}, high[3] = {-1, -1, -1};
    int ok = 1;
    Py_BEGIN_ALLOW_THREADS
    if (n > 0) ok = extent((const float *)points.buf, columns, n, cell, low, high);
    Py_END_ALLOW_THREADS
    if (ok) {
        result = Py_BuildValue("(LLL)(LLL)", (long long)low[0], (long long)low[1], (long long)low[2],
                               (long long)high[0], (long long)high[1], (long long)high[2]);
    } else {
        result = Py_None;
        Py_INCREF(result);
    }
done:
    PyBuffer_Release(&points);
    return result;
}

static PyObject *py_grid_fill(PyObject *self, PyObject *args) {
    Py_buffer points, starts, sorted_xyz, sorted_rows, cell_of;
    Py_ssize_t columns;
    double cell;
    long long low[3], size[3];
    (void)self;
    if (!PyArg_ParseTuple(args, "y*nd(LLL)(LLL)w*w*w*w*", &points, &columns, &cell, &low[0], &low[1], &low[2],
                          &size[0], &size[1], &size[2], &starts, &sorted_xyz, &sorted_rows, &cell_of)) {
        return NULL;
    }
    PyObject *result = NULL;
    const Py_ssize_t n = columns >= 3 ? points.len / (columns * (Py_ssize_t)sizeof(float)) : 0;
    const long long cells = size[0] * size[1] * size[2];
    if (columns < 3 || points.len != n * columns * (Py_ssize_t)sizeof(float) || !(cell > 0.0) || size[0] < 1 ||
        size[1] < 1 || size[2] < 1 || n >= INT32_MAX || starts.len != (cells + 1) * (Py_ssize_t)sizeof(int32_t) ||
        sorted_xyz.len != 3 * n * (Py_ssize_t)sizeof(double) || sorted_rows.len != n * (Py_ssize_t)sizeof(int64_t) ||
        cell_of.len != n * (Py_ssize_t)sizeof(int64_t)) {
        PyErr_SetString(PyExc_ValueError, "grid_fill: inconsistent buffers (see geometry_kernels.c)");
        goto done;
    }
    const int64_t lo[3] = {low[0], low[1], low[2]}, sz[3] = {size[0], size[1], size[2]};
    Py_BEGIN_ALLOW_THREADS
    fill((const float *)points.buf, columns, n, cell, lo, sz, (int32_t *)starts.buf, (double *)sorted_xyz.buf,
         (int64_t *)sorted_rows.buf, (int64_t *)cell_of.buf);
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&points);
    PyBuffer_Release(&starts);
    PyBuffer_Release(&sorted_xyz);
    PyBuffer_Release(&sorted_rows);
    PyBuffer_Release(&cell_of);
    return result;
}

/* The grid of grid_fill's buffers, checked against each other; 0 (a ValueError set) when they disagree. */
static int grid_view(Grid *grid, double cell, const long long *low, const long long *size, const Py_buffer *starts,
                     const Py_buffer *sorted_xyz, const Py_buffer *sorted_rows, const char *caller) {
    const Py_ssize_t n = sorted_rows->len / (Py_ssize_t)sizeof(int64_t);
    const long long cells = size[0] * size[1] * size[2];
    if (!(cell > 0.0) || size[0] < 1 || size[1] < 1 || size[2] < 1 ||
        starts->len != (cells + 1) * (Py_ssize_t)sizeof(int32_t) ||
        sorted_xyz->len != 3 * n * (Py_ssize_t)sizeof(double) || ((const int32_t *)starts->buf)[cells] != n) {
        PyErr_Format(PyExc_ValueError, "%s: the grid's buffers disagree (see geometry_kernels.c)", caller);
        return 0;
    }
    *grid = (Grid){cell, low[0], low[1], low[2], size[0], size[1], size[2], (const int32_t *)starts->buf,
                   (const double *)sorted_xyz->buf, (const int64_t *)sorted_rows->buf};
    return 1;
}

/* The number of queries (m, columns >= 3) float32 in `queries`, with `per_query` int64 in index and one uint8 in
   status each; -1 (a ValueError set) when the buffers disagree. */
static Py_ssize_t query_count(const Py_buffer *queries, Py_ssize_t columns, const Py_buffer *status,
                              const Py_buffer *index, Py_ssize_t per_query, const char *caller) {
    const Py_ssize_t m = columns >= 3 ? queries->len / (columns * (Py_ssize_t)sizeof(float)) : 0;
    if (columns < 3 || queries->len != m * columns * (Py_ssize_t)sizeof(float) || status->len != m ||
        index->len != m * per_query * (Py_ssize_t)sizeof(int64_t)) {
        PyErr_Format(PyExc_ValueError, "%s: queries, status and index disagree (see geometry_kernels.c)", caller);
        return -1;
    }
    return m;
}

static void release(Py_buffer *buffers, int count) {
    for (int i = 0; i < count; ++i) PyBuffer_Release(&buffers[i]);
}

/* (the buffers of grid_nearest and grid_nearest_one, in their order) */
enum { STARTS, SORTED_XYZ, SORTED_ROWS, QUERIES, STATUS, INDEX, BUFFERS };

static PyObject *py_grid_nearest(PyObject *self, PyObject *args) {
    Py_buffer b[BUFFERS];
    Py_ssize_t query_columns, k;
    double cell, search_sq, gate_sq;
    long long low[3], size[3];
    (void)self;
    if (!PyArg_ParseTuple(args, "d(LLL)(LLL)y*y*y*y*nnddw*w*", &cell, &low[0], &low[1], &low[2], &size[0], &size[1],
                          &size[2], &b[STARTS], &b[SORTED_XYZ], &b[SORTED_ROWS], &b[QUERIES], &query_columns, &k,
                          &search_sq, &gate_sq, &b[STATUS], &b[INDEX])) {
        return NULL;
    }
    Grid grid;
    Py_ssize_t m = -1;
    if (k < 1 || k > MAX_K) {
        PyErr_SetString(PyExc_ValueError, "grid_nearest: k must lie in [1, 64]");
    } else if (grid_view(&grid, cell, low, size, &b[STARTS], &b[SORTED_XYZ], &b[SORTED_ROWS], "grid_nearest")) {
        m = query_count(&b[QUERIES], query_columns, &b[STATUS], &b[INDEX], k, "grid_nearest");
    }
    if (m >= 0) {
        Py_BEGIN_ALLOW_THREADS
        nearest(&grid, (const float *)b[QUERIES].buf, query_columns, m, k, search_sq, gate_sq,
                (uint8_t *)b[STATUS].buf, (int64_t *)b[INDEX].buf);
        Py_END_ALLOW_THREADS
    }
    release(b, BUFFERS);
    if (m < 0) return NULL;
    Py_RETURN_NONE;
}

static void nearest_one(const Grid *grid, const float *queries, Py_ssize_t query_columns, Py_ssize_t m,
                        int64_t max_shell, double gate_sq, uint8_t *status, int64_t *index) {
    for (Py_ssize_t row = 0; row < m; ++row) {
        double q[3];
        int64_t cell[3];
        status[row] = 0;
        if (!query_cell(grid, queries + row * query_columns, q, cell)) continue;
        const int64_t qi = cell[0], qj = cell[1], qk = cell[2];
        double best = INFINITY, second = INFINITY;
        int64_t which = -1;
        for (int64_t shell = 0; shell <= max_shell; ++shell) {
            for (int64_t di = -shell; di <= shell; ++di) {
                for (int64_t dj = -shell; dj <= shell; ++dj) {
                    /* on the shell's side faces the whole column of it; inside them its top and bottom cells */
                    const int side = (di == -shell || di == shell || dj == -shell || dj == shell);
                    for (int part = 0; part < (side || shell == 0 ? 1 : 2); ++part) {
                        int64_t k_low, k_high, begin, end;
                        if (side) {
                            k_low = qk - shell;
                            k_high = qk + shell;
                        } else {
                            k_low = k_high = part == 0 ? qk - shell : qk + shell;
                        }
                        if (!column_run(grid, qi + di, qj + dj, k_low, k_high, &begin, &end)) continue;
                        for (int64_t at = begin; at < end; ++at) {
                            const double d2 = squared_distance(grid->sorted_xyz + 3 * at, q);
                            if (d2 < best) {
                                second = best;
                                best = d2;
                                which = grid->sorted_rows[at];
                            } else if (d2 < second) {
                                second = d2;
                            }
                        }
                    }
                }
            }
            /* Every point outside shells 0..s lies at least s cells from the query (less a rounding margin). */
            const double reach = (double)shell * grid->cell * (1.0 - 1e-9) - 1e-9;
            if (which >= 0 && sqrt(best) < reach) break;
        }
        if (which < 0) continue;
        const double nearest = sqrt(best);
        if (!(nearest * nearest < gate_sq)) continue;
        status[row] = second == best ? 2 : 1;
        index[row] = which;
    }
}

static PyObject *py_grid_nearest_one(PyObject *self, PyObject *args) {
    Py_buffer b[BUFFERS];
    Py_ssize_t query_columns, max_shell;
    double cell, gate_sq;
    long long low[3], size[3];
    (void)self;
    if (!PyArg_ParseTuple(args, "d(LLL)(LLL)y*y*y*y*nndw*w*", &cell, &low[0], &low[1], &low[2], &size[0], &size[1],
                          &size[2], &b[STARTS], &b[SORTED_XYZ], &b[SORTED_ROWS], &b[QUERIES], &query_columns,
                          &max_shell, &gate_sq, &b[STATUS], &b[INDEX])) {
        return NULL;
    }
    Grid grid;
    Py_ssize_t m = -1;
    if (max_shell < 0) {
        PyErr_SetString(PyExc_ValueError, "grid_nearest_one: max_shell must not be negative");
    } else if (grid_view(&grid, cell, low, size, &b[STARTS], &b[SORTED_XYZ], &b[SORTED_ROWS], "grid_nearest_one")) {
        m = query_count(&b[QUERIES], query_columns, &b[STATUS], &b[INDEX], 1, "grid_nearest_one");
    }
    if (m >= 0) {
        Py_BEGIN_ALLOW_THREADS
        nearest_one(&grid, (const float *)b[QUERIES].buf, query_columns, m, max_shell, gate_sq,
                    (uint8_t *)b[STATUS].buf, (int64_t *)b[INDEX].buf);
        Py_END_ALLOW_THREADS
    }
    release(b, BUFFERS);
    if (m < 0) return NULL;
    Py_RETURN_NONE;
}

#define PAIR_GRID_MAX_CELLS (1LL << 24)

static Py_ssize_t pairs(const double *xy, Py_ssize_t n, double radius, int64_t *first, int64_t *second,
                        Py_ssize_t capacity) {
    if (n < 2) return 0;
    const double cell = radius * (1.0 + 1e-6); /* (a cell spans the radius: pairs lie in neighbouring cells) */
    double lo[2] = {INFINITY, INFINITY}, hi[2] = {-INFINITY, -INFINITY};
    for (Py_ssize_t i = 0; i < n; ++i) {
        for (int a = 0; a < 2; ++a) {
            const double c = floor(xy[2 * i + a] / cell);
            if (!(fabs(c) < GRID_MAX_INDEX)) return -1;
            if (c < lo[a]) lo[a] = c;
            if (c > hi[a]) hi[a] = c;
        }
    }
    const int64_t ni = (int64_t)(hi[0] - lo[0]) + 1, nj = (int64_t)(hi[1] - lo[1]) + 1;
    if (ni > PAIR_GRID_MAX_CELLS / nj) return -1;
    int64_t *starts = calloc((size_t)(ni * nj + 1), sizeof(int64_t));
    int64_t *cell_of = malloc((size_t)n * sizeof(int64_t));
    int64_t *sorted = malloc((size_t)n * sizeof(int64_t));
    if (starts == NULL || cell_of == NULL || sorted == NULL) {
        free(starts);
        free(cell_of);
        free(sorted);
        return -2;
    }
    for (Py_ssize_t i = 0; i < n; ++i) {
        const int64_t ci = (int64_t)(floor(xy[2 * i] / cell) - lo[0]);
        const int64_t cj = (int64_t)(floor(xy[2 * i + 1] / cell) - lo[1]);
        cell_of[i] = ci * nj + cj;
        starts[cell_of[i] + 1] += 1;
    }
    for (int64_t c = 0; c < ni * nj; ++c) starts[c + 1] += starts[c];
    for (Py_ssize_t i = 0; i < n; ++i) sorted[starts[cell_of[i]]++] = (int64_t)i; /* (each cell in index order) */
    for (int64_t c = ni * nj; c > 0; --c) starts[c] = starts[c - 1];
    starts[0] = 0;
    const double radius_sq = radius * radius;
    Py_ssize_t count = 0;
    for (Py_ssize_t i = 0; i < n; ++i) {
        const int64_t ci = cell_of[i] / nj, cj = cell_of[i] % nj;
        const double x = xy[2 * i], y = xy[2 * i + 1];
        for (int64_t a = ci - 1; a <= ci + 1; ++a) {
            if (a < 0 || a >= ni) continue;
            for (int64_t b = cj - 1; b <= cj + 1; ++b) {
                if (b < 0 || b >= nj) continue;
                const int64_t c = a * nj + b;
                for (int64_t at = starts[c]; at < starts[c + 1]; ++at) {
                    const int64_t j = sorted[at];
                    if (j <= i) continue;
                    const double dx = x - xy[2 * j], dy = y - xy[2 * j + 1];
                    double d2 = dx * dx;
                    d2 += dy * dy;
                    if (!(d2 <= radius_sq)) continue;
                    if (count < capacity) {
                        first[count] = (int64_t)i;
                        second[count] = j;
                    }
                    ++count;
                }
            }
        }
    }
    free(starts);
    free(cell_of);
    free(sorted);
    return count;
}

static PyObject *py_pairs_within(PyObject *self, PyObject *args) {
    Py_buffer xy, first, second;
    double radius;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*dw*w*", &xy, &radius, &first, &second)) return NULL;
    PyObject *result = NULL;
    const Py_ssize_t n = xy.len / (2 * (Py_ssize_t)sizeof(double));
    const Py_ssize_t capacity = first.len / (Py_ssize_t)sizeof(int64_t);
    if (xy.len != n * 2 * (Py_ssize_t)sizeof(double) || first.len != second.len ||
        first.len != capacity * (Py_ssize_t)sizeof(int64_t) || !(radius > 0.0)) {
        PyErr_SetString(PyExc_ValueError, "pairs_within: xy must be (n, 2) float64, first and second int64 alike");
        goto done;
    }
    Py_ssize_t count;
    Py_BEGIN_ALLOW_THREADS
    count = pairs((const double *)xy.buf, n, radius, (int64_t *)first.buf, (int64_t *)second.buf, capacity);
    Py_END_ALLOW_THREADS
    if (count == -2) {
        PyErr_NoMemory();
        goto done;
    }
    result = PyLong_FromSsize_t(count);
done:
    PyBuffer_Release(&xy);
    PyBuffer_Release(&first);
    PyBuffer_Release(&second);
    return result;
}

static PyMethodDef methods[] = {
    {"plane_fits", py_plane_fits, METH_VARARGS, "Least-squares planes through neighbourhoods (see the file)."},
    {"line_fits", py_line_fits, METH_VARARGS, "Principal directions of neighbourhoods (see the file)."},
    {"map_plane_terms", py_map_plane_terms, METH_VARARGS, "Point-to-plane terms of the mapping (see the file)."},
    {"map_line_terms", py_map_line_terms, METH_VARARGS, "Point-to-line terms of the mapping (see the file)."},
    {"grid_extent", py_grid_extent, METH_VARARGS, "The cells a point set spans (see the file)."},
    {"grid_fill", py_grid_fill, METH_VARARGS, "Sorts points by cell (see the file)."},
    {"grid_nearest", py_grid_nearest, METH_VARARGS, "k nearest points of each query (see the file)."},
    {"grid_nearest_one", py_grid_nearest_one, METH_VARARGS, "The nearest point of each query (see the file)."},
    {"pairs_within", py_pairs_within, METH_VARARGS, "The pairs of 2D points within a radius (see the file)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_geometry_kernels", NULL, -1, methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__geometry_kernels(void) { return PyModule_Create(&module); }
