/*
 * featureAssociation's inner loops that NumPy can only express with many small calls or not at all, in C with
 * the same float32 and float64 arithmetic as the NumPy code they replace, operation by operation (built with
 * -ffp-contract=off: no fused multiply-adds). The modules that call them (core/odometry/features.py,
 * correspondences.py, sweep.py, core/imu/buffer.py) keep the NumPy/Python versions as the fallback when this
 * extension is not built, and tests/test_feature_kernels.py compares the two bit for bit.
 *
 * select_features(edges, edge_bounds, flats, flat_bounds, jumps, half_window, taken, edge_num, less_edge_num,
 *                 surf_num, sharp, less_sharp, less_sharp_region, flat) -> (number of sharp, less sharp, flat)
 *   The greedy part of the feature extraction, sequential by nature: in each sub-region the candidates are
 *   visited in curvature order and every pick suppresses its neighbours for the picks after it: up to
 *   half_window points on each side, stopping at a column jump (jumps: sorted int64, 0 and n included, the j
 *   where the column jumps between points j - 1 and j), the slice features._suppression_slices gives. Index
 *   arrays are contiguous int64; *_bounds hold regions + 1 entries (region r: [bounds[r], bounds[r + 1])); taken
 *   is a writable uint8 array of the n points (1: picked or suppressed); the four outputs are int64 arrays large
 *   enough for regions x the per-region limits. A negative candidate index reads point index + n, as Python
 *   indexing does, and its slice is normalised as a Python slice; every slice is kept within [0, n].
 *
 * nearest_in_segments(xyz_rows, query, position, lengths, limit, index, best)
 *   For each window segment (lengths: int64, 4 per query, back to back; position: the last cloud's point
 *   indices of all segments, int64), the point nearest to its query: squared distance (dx^2 + dy^2) + dz^2 in
 *   float32 from xyz_rows (3, N) float32 and query (n, 3) float32; ties go to the first point of a forward
 *   segment (kinds 2 and 3) and the last of a backward one (kinds 0 and 1), as the original's scans meet
 *   them. Writes index (int64, -1: none) and best (float32, inf: none) for every segment; only distances
 *   below limit count.
 *
 * nearest_in_windows(xyz_rows, rings, query, closest, ring_window, forward_bound, kinds, limit, index, best)
 *   The whole window search of a last cloud whose rings (int64, one per point) ascend, for each query (n, 3)
 *   float32 and its nearest point closest (int64): the index windows of LastCloud.window, cut into the four
 *   segments of LastCloud.segments (only the kinds whose bit is set in kinds: bit k for kind k), and the
 *   nearest point of each as nearest_in_segments finds it, without building the index arrays. Writes index
 *   (int64, n x 4) and best (float32, n x 4) as nearest_in_segments does.
 *
 * sweep_rows(per_point, coeff, active, out)
 *   SweepStartFrame.rows in one pass: per_point (13, n) float64 holds cx, sx, cy, sy, cz, sz, s, qx, qy, qz, ux,
 *   uy, vz of the frame, coeff (n, m, 3) float64 the m coefficient vectors of each point, active (k,) int64 the
 *   parameters (0-5); writes out (k, n * m) float64, the rows column by column.
 *
 * sweep_frame(xyz, s, t, cx, cy, cz, sx, sy, sz, block, start)
 *   SweepStartFrame's partial products and start points in one pass: xyz (3, n), s (n,), t (3,) the translation
 *   and the six (n,) cosines and sines, all float64; writes block (14, n) float64 = cx, sx, cy, sy, cz, sz, s, qx,
 *   qy, qz, ux, uy, vz, vy (its first 13 rows are sweep_rows' per_point) and start (n, 3) float32.
 *
 * euler_rotate(left, cosines, sines, xyz, out)
 *   core.frames.rotate_by_euler after its sines and cosines: left (3, 3), cosines and sines (3, n) of the angles
 *   (rx, ry, rz), all float64, xyz (n, c >= 3) float32 points; writes out (3, n) float64, the rows of
 *   (left @ Ry Rx Rz) @ p in rotate_by_euler's order (the entries of Ry Rx Rz, left @ them summed j = 0, 1, 2,
 *   then (x + z) + y + 0.0).
 *
 * imu_lerp(table, times, out, max_reach, stamp_rounding, rate)
 *   ImuBuffer._bracket, _lerp_attitude and _carry_on in one pass: table (m >= 1, 13) float64 the buffer's rows
 *   (time, roll, pitch, yaw, ...), times (n,) float64, rate (3,) float64 the newest rates of roll, pitch and yaw;
 *   writes out (n, 3) float64 roll, pitch, yaw. NumPy's semantics throughout: searchsorted's order puts NaN last
 *   (each time's bracket tried first where the previous one's ended: times mostly ascend), clip keeps NaN and
 *   -0.0, the yaw unwrapped as the where()s do; when a time lies more than stamp_rounding beyond the newest
 *   sample, every row gets rate times its reach beyond it (at most max_reach; 0 for the others) added, as
 *   _carry_on's arrays do.
 *
 * imu_rotate_at(table, times, max_reach, stamp_rounding, rate, left, xyz, out)
 *   imu_rotate(left, *ImuBuffer.attitude(times), xyz) in one pass: imu_lerp's attitudes, libm's cosines and sines
 *   of (pitch, yaw, roll) (NumPy's np.cos and np.sin of float64 are libm's), then euler_rotate's products; out
 *   (3, n) float64. Runs without the GIL.
 * imu_sample(stamp, orientation, rate, acceleration, last, time_offset, reset_after, scan_period, gravity,
 *            quaternion_tolerance, max_rate, max_acceleration, gyro_state, gyro_bias)
 *   ImuBuffer.add's common case, its row (a 13-tuple: time, roll, pitch, yaw, velocity, shift, angle) or None for
 *   every other case, which the Python code then takes: a sample it would reject (non-finite, not a unit
 *   quaternion, beyond the rate or acceleration bounds), one not newer than last (the previous row, a 13-tuple,
 *   or None for the first sample) or far older (a restart). orientation (x, y, z, w), rate and acceleration are
 *   sequences of numbers. gyro_state (13,) float64 (GyroAttitude.state, updated in place) and gyro_bias (3,)
 *   float64, or None and None for the orientation field's attitude. The same operations as ImuBuffer.add and
 *   GyroAttitude.update, in their order, with libm's functions (Python's math module calls the same ones).
 *
 * line_term(start, last, index1, index2, weighted, weight_gain, min_weight, chosen, anchor, along, weight, coeff)
 *   -> number kept
 *   The sweep-start odometry's line correspondences made into its residual terms (SweepStartOdometry._term,
 *   'corner'): for each point i of start (n, >= 3 columns) float32 with index2[i] >= 0 (int64; index1 and index2
 *   the points of last (m, >= 3) float32 spanning its line), the line's anchor a = last[index1] and unit direction
 *   (a - b) / |a - b| in float64, the point's perpendicular distance to it, the weight 1 - weight_gain * distance
 *   (1 unless weighted), and, where that weight exceeds min_weight and the distance and direction are finite,
 *   writes the point's index to chosen (n,) int64 and, at the same row, anchor and along (n, 3), weight (n,) and
 *   the weighted projector rows (I - u u^T) w to coeff (n, 3, 3), all float64. NumPy's operations in its order:
 *   the norms' sums from the first component on, the offsets' dot product as np.einsum's ((x0 + x2) + x1).
 *
 * occluded(ranges, columns, half_window, column_gap, depth_jump, parallel_ratio, picked)
 *   features.occluded_mask in one pass: ranges (n,) float32, columns (n,) int64; marks picked (n,) bool (zeroed
 *   by the caller) where the NumPy version does, with its dtypes (differences of float32 ranges in float64
 *   against the float32 depth_jump; the parallel-beam differences in float32 against parallel_ratio * range in
 *   float64).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <math.h>
#include <string.h>

#include "sweep_jacobian.h"

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#define N_BUFFERS 10

/* taken[start:stop] = 1, within the array whatever the slice says. */
static inline void mark(uint8_t *taken, Py_ssize_t n, int64_t start, int64_t stop) {
    if (start < 0) start = 0;
    if (stop > n) stop = n;
    if (stop > start) memset(taken + start, 1, (size_t)(stop - start));
}

/* First entry of the sorted jumps[0, count) that is >= value (count if none). */
static inline Py_ssize_t first_at_least(const int64_t *jumps, Py_ssize_t count, int64_t value) {
    Py_ssize_t lo = 0, hi = count;
    while (lo < hi) {
        Py_ssize_t mid = lo + (hi - lo) / 2;
        if (jumps[mid] < value) {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    return lo;
}

/* Marks the suppression slice of a pick at index (see the file comment; k = the point it reads, in [0, n)). */
static void suppress(uint8_t *taken, Py_ssize_t n, const int64_t *jumps, Py_ssize_t n_jumps, int64_t half_window,
                     int64_t index, int64_t k) {
    Py_ssize_t ahead = first_at_least(jumps, n_jumps, k + 1 < n ? k + 1 : n);
    Py_ssize_t behind = first_at_least(jumps, n_jumps, k + 1) - 1; /* the last jump <= k */
    int64_t forward = (ahead < n_jumps ? jumps[ahead] : n) - k - 1;
    int64_t backward = k - (behind >= 0 ? jumps[behind] : 0);
    forward = forward < half_window ? forward : half_window;
    backward = backward < half_window ? backward : half_window;
    int64_t start = index - backward, stop = index + forward + 1;
    if (index < 0) {
        start = start < 0 ? start + n : start;
        stop = stop < 0 ? stop + n : stop;
        stop = stop < start ? start : stop;
    }
    mark(taken, n, start, stop);
}

static PyObject *py_select_features(PyObject *self, PyObject *args) {
    (void)self;
    Py_buffer b[N_BUFFERS];
    long long half_window, edge_num, less_edge_num, surf_num;
    memset(b, 0, sizeof(b));
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*Lw*LLLw*w*w*w*", &b[0], &b[1], &b[2], &b[3], &b[4], &half_window, &b[5],
                          &edge_num, &less_edge_num, &surf_num, &b[6], &b[7], &b[8], &b[9])) {
        return NULL;
    }
    PyObject *result = NULL;
    const int64_t *edges = b[0].buf, *edge_bounds = b[1].buf, *flats = b[2].buf, *flat_bounds = b[3].buf;
    const int64_t *jumps = b[4].buf;
    uint8_t *taken = b[5].buf;
    int64_t *sharp = b[6].buf, *less_sharp = b[7].buf, *less_region = b[8].buf, *flat = b[9].buf;
    Py_ssize_t n = b[5].len, n_jumps = b[4].len / 8;
    Py_ssize_t regions = b[1].len / 8 - 1;
    Py_ssize_t n_edges = b[0].len / 8, n_flats = b[2].len / 8;
    if (regions < 0 || b[3].len != b[1].len || edge_bounds[regions] > n_edges || flat_bounds[regions] > n_flats ||
        b[6].len / 8 < regions * edge_num || b[7].len / 8 < regions * less_edge_num || b[8].len != b[7].len ||
        b[9].len / 8 < regions * surf_num) {
        PyErr_SetString(PyExc_ValueError, "select_features: inconsistent buffer sizes");
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
            suppress(taken, n, jumps, n_jumps, half_window, edges[i], k);
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
            suppress(taken, n, jumps, n_jumps, half_window, flats[i], k);
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

static PyObject *py_nearest_in_segments(PyObject *self, PyObject *args) {
    Py_buffer rows, query, position, lengths, index, best;
    float limit;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*y*y*fw*w*", &rows, &query, &position, &lengths, &limit, &index, &best)) {
        return NULL;
    }
    PyObject *result = NULL;
    Py_ssize_t n_points = rows.len / (3 * (Py_ssize_t)sizeof(float));
    Py_ssize_t n_segments = lengths.len / 8, n_positions = position.len / 8;
    const float *x = rows.buf, *y = x + n_points, *z = y + n_points, *q = query.buf;
    const int64_t *pos = position.buf, *len = lengths.buf;
    int64_t *out_index = index.buf;
    float *out_best = best.buf;
    if (rows.len != 3 * n_points * (Py_ssize_t)sizeof(float) || n_segments % 4 != 0 ||
        query.len != (n_segments / 4) * 3 * (Py_ssize_t)sizeof(float) || index.len != lengths.len ||
        best.len != n_segments * (Py_ssize_t)sizeof(float)) {
        PyErr_SetString(PyExc_ValueError, "nearest_in_segments: inconsistent buffer sizes");
        goto done;
    }
    Py_ssize_t at = 0;
    for (Py_ssize_t segment = 0; segment < n_segments; ++segment) {
        const float *p = q + 3 * (segment / 4);
        int backward = segment % 4 < 2;
        int64_t chosen = -1;
        float nearest = INFINITY;
        if (len[segment] < 0 || at + len[segment] > n_positions) {
            PyErr_SetString(PyExc_ValueError, "nearest_in_segments: segments beyond the positions");
            goto done;
        }
        for (int64_t k = 0; k < len[segment]; ++k, ++at) {
            int64_t j = pos[at];
            if (j < 0 || j >= n_points) {
                PyErr_SetString(PyExc_IndexError, "nearest_in_segments: position outside the cloud");
                goto done;
            }
            float dx = x[j] - p[0], dy = y[j] - p[1], dz = z[j] - p[2];
            float d = dx * dx + dy * dy;
            d = d + dz * dz;
            if (d < nearest || (backward && d == nearest && chosen >= 0)) {
                nearest = d;
                chosen = j;
            }
        }
        if (!(nearest < limit)) {
            chosen = -1;
            nearest = INFINITY;
        }
        out_index[segment] = chosen;
        out_best[segment] = nearest;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&rows);
    PyBuffer_Release(&query);
    PyBuffer_Release(&position);
    PyBuffer_Release(&lengths);
    PyBuffer_Release(&index);
    PyBuffer_Release(&best);
    return result;
}

/* Squared distance of point j to p, (dx^2 + dy^2) + dz^2 in float32. */
static inline float squared_distance(const float *x, const float *y, const float *z, const float *p, int64_t j) {
    float dx = x[j] - p[0], dy = y[j] - p[1], dz = z[j] - p[2];
    float d = dx * dx + dy * dy;
    return d + dz * dz;
}

/*
 * The nearest point of [start, stop) to p as the original's scan keeps it: the smallest squared distance
 * (squared_distance), at the first index that has it (the last one in a backward segment); chosen -1 and INFINITY
 * when none is below infinity. The minimum is taken four distances at a time where SSE2 is there: the same float32
 * operations per distance, and minps keeps d < best ? d : best as the scalar scan does (a NaN never wins; no
 * distance is -0.0), so it is the same minimum; the index is then the first (last) that has it.
 */
static inline float segment_nearest(const float *x, const float *y, const float *z, const float *p, int64_t start,
                                    int64_t stop, int backward, int64_t *chosen) {
    float nearest = INFINITY;
    int64_t j = start;
#if defined(__SSE2__)
    const __m128 px = _mm_set1_ps(p[0]), py = _mm_set1_ps(p[1]), pz = _mm_set1_ps(p[2]);
    __m128 best = _mm_set1_ps(INFINITY);
    for (; j + 4 <= stop; j += 4) {
        __m128 dx = _mm_sub_ps(_mm_loadu_ps(x + j), px);
        __m128 dy = _mm_sub_ps(_mm_loadu_ps(y + j), py);
        __m128 dz = _mm_sub_ps(_mm_loadu_ps(z + j), pz);
        __m128 d = _mm_add_ps(_mm_mul_ps(dx, dx), _mm_mul_ps(dy, dy));
        d = _mm_add_ps(d, _mm_mul_ps(dz, dz));
        best = _mm_min_ps(d, best);
    }
    float lanes[4];
    _mm_storeu_ps(lanes, best);
    for (int k = 0; k < 4; ++k) {
        nearest = lanes[k] < nearest ? lanes[k] : nearest;
    }
#endif
    for (; j < stop; ++j) {
        float d = squared_distance(x, y, z, p, j);
        nearest = d < nearest ? d : nearest;
    }
    *chosen = -1;
    if (nearest < INFINITY) {
        if (backward) {
            for (j = stop - 1; j >= start; --j) {
                if (squared_distance(x, y, z, p, j) == nearest) {
                    *chosen = j;
                    break;
                }
            }
        } else {
            for (j = start; j < stop; ++j) {
                if (squared_distance(x, y, z, p, j) == nearest) {
                    *chosen = j;
                    break;
                }
            }
        }
    }
    return nearest;
}

/* First index in [0, n) whose ring is >= value (strict: > value), n if none: NumPy's searchsorted, left (right). */
static inline int64_t ring_bound(const int64_t *rings, int64_t n, int64_t value, int strict) {
    int64_t low = 0, high = n;
    while (low < high) {
        int64_t middle = low + (high - low) / 2;
        if (strict ? rings[middle] <= value : rings[middle] < value) {
            low = middle + 1;
        } else {
            high = middle;
        }
    }
    return low;
}

static PyObject *py_nearest_in_windows(PyObject *self, PyObject *args) {
    Py_buffer rows, rings_buffer, query, closest_buffer, index, best;
    long long ring_window, forward_bound;
    int kinds;
    float limit;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*y*y*LLifw*w*", &rows, &rings_buffer, &query, &closest_buffer, &ring_window,
                          &forward_bound, &kinds, &limit, &index, &best)) {
        return NULL;
    }
    PyObject *result = NULL;
    Py_ssize_t n_points = rows.len / (3 * (Py_ssize_t)sizeof(float));
    Py_ssize_t n_queries = closest_buffer.len / 8;
    const float *x = rows.buf, *y = x + n_points, *z = y + n_points, *q = query.buf;
    const int64_t *rings = rings_buffer.buf, *closest = closest_buffer.buf;
    int64_t *out_index = index.buf;
    float *out_best = best.buf;
    if (rows.len != 3 * n_points * (Py_ssize_t)sizeof(float) || rings_buffer.len != n_points * 8 ||
        query.len != n_queries * 3 * (Py_ssize_t)sizeof(float) || index.len != n_queries * 4 * 8 ||
        best.len != n_queries * 4 * (Py_ssize_t)sizeof(float)) {
        PyErr_SetString(PyExc_ValueError, "nearest_in_windows: inconsistent buffer sizes");
        goto done;
    }
    for (Py_ssize_t i = 0; i < n_queries; ++i) {
        int64_t c = closest[i];
        if (c < 0 || c >= n_points) {
            PyErr_SetString(PyExc_IndexError, "nearest_in_windows: nearest point outside the cloud");
            goto done;
        }
        int64_t ring = rings[c];
        /* LastCloud.window: forward [c + 1, hi), backward (lo, c - 1]. */
        int64_t hi = ring_bound(rings, n_points, ring + ring_window, 1);
        int64_t lo = ring_bound(rings, n_points, ring - ring_window, 0);
        lo = (lo < c ? lo : c) - 1;
        hi = hi < forward_bound ? hi : forward_bound;
        hi = hi > c + 1 ? hi : c + 1;
        /* LastCloud.segments: the cuts between other rings and the nearest point's own, clipped to the windows. */
        int64_t backward_cut = ring_bound(rings, n_points, ring, 0);
        backward_cut = backward_cut > lo + 1 ? backward_cut : lo + 1;
        backward_cut = backward_cut < c ? backward_cut : c;
        int64_t forward_cut = ring_bound(rings, n_points, ring, 1);
        forward_cut = forward_cut > c + 1 ? forward_cut : c + 1;
        forward_cut = forward_cut < hi ? forward_cut : hi;
        const int64_t starts[4] = {lo + 1, backward_cut, c + 1, forward_cut};
        const int64_t stops[4] = {backward_cut, c, forward_cut, hi};
        const float *p = q + 3 * i;
        for (int kind = 0; kind < 4; ++kind) {
            int64_t chosen = -1;
            float nearest = INFINITY;
            if (kinds & (1 << kind)) {
                nearest = segment_nearest(x, y, z, p, starts[kind], stops[kind], kind < 2, &chosen);
            }
            if (!(nearest < limit)) {
                chosen = -1;
                nearest = INFINITY;
            }
            out_index[4 * i + kind] = chosen;
            out_best[4 * i + kind] = nearest;
        }
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&rows);
    PyBuffer_Release(&rings_buffer);
    PyBuffer_Release(&query);
    PyBuffer_Release(&closest_buffer);
    PyBuffer_Release(&index);
    PyBuffer_Release(&best);
    return result;
}

static PyObject *py_sweep_rows(PyObject *self, PyObject *args) {
    Py_buffer per_point, coeff, active_buffer, out;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*y*w*", &per_point, &coeff, &active_buffer, &out)) {
        return NULL;
    }
    PyObject *result = NULL;
    Py_ssize_t n = per_point.len / (13 * (Py_ssize_t)sizeof(double));
    Py_ssize_t k = active_buffer.len / 8;
    Py_ssize_t m = n > 0 ? coeff.len / (n * 3 * (Py_ssize_t)sizeof(double)) : 0;
    const int64_t *active = active_buffer.buf;
    if (per_point.len != n * 13 * (Py_ssize_t)sizeof(double) || coeff.len != n * m * 3 * (Py_ssize_t)sizeof(double) ||
        out.len != k * n * m * (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, "sweep_rows: inconsistent buffer sizes");
        goto done;
    }
    for (Py_ssize_t j = 0; j < k; ++j) {
        if (active[j] < 0 || active[j] > 5) {
            PyErr_SetString(PyExc_ValueError, "sweep_rows: parameters are 0 to 5");
            goto done;
        }
    }
    const double *v = per_point.buf, *a = coeff.buf;
    double *o = out.buf;
    const Py_ssize_t stride = n * m;
    for (Py_ssize_t i = 0; i < n; ++i) {
        const double cx = v[i], sx = v[n + i], cy = v[2 * n + i], sy = v[3 * n + i], cz = v[4 * n + i];
        const double sz = v[5 * n + i], s = v[6 * n + i], qx = v[7 * n + i], qy = v[8 * n + i], qz = v[9 * n + i];
        const double ux = v[10 * n + i], uy = v[11 * n + i], vz = v[12 * n + i];
        for (Py_ssize_t c = 0; c < m; ++c) {
            const double *row = a + 3 * (i * m + c);
            for (Py_ssize_t j = 0; j < k; ++j) {
                o[j * stride + i * m + c] = sweep_jacobian_entry((int)active[j], row[0], row[1], row[2], cx, sx, cy, sy,
                                                                 cz, sz, s, qx, qy, qz, ux, uy, vz);
            }
        }
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&per_point);
    PyBuffer_Release(&coeff);
    PyBuffer_Release(&active_buffer);
    PyBuffer_Release(&out);
    return result;
}

static PyObject *py_sweep_frame(PyObject *self, PyObject *args) {
    Py_buffer b[11];
    (void)self;
    memset(b, 0, sizeof(b));
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*y*y*y*w*w*", &b[0], &b[1], &b[2], &b[3], &b[4], &b[5], &b[6], &b[7],
                          &b[8], &b[9], &b[10])) {
        return NULL;
    }
    PyObject *result = NULL;
    Py_ssize_t n = b[1].len / (Py_ssize_t)sizeof(double);
    Py_ssize_t bytes = n * (Py_ssize_t)sizeof(double);
    int ok = b[0].len == 3 * bytes && b[2].len == 3 * (Py_ssize_t)sizeof(double) && b[9].len == 14 * bytes &&
             b[10].len == n * 3 * (Py_ssize_t)sizeof(float);
    for (int i = 3; i < 9; ++i) {
        ok = ok && b[i].len == bytes;
    }
    if (!ok) {
        PyErr_SetString(PyExc_ValueError, "sweep_frame: inconsistent buffer sizes");
        goto done;
    }
    const double *x = b[0].buf, *y = x + n, *z = y + n, *s = b[1].buf, *t = b[2].buf;
    const double *cx = b[3].buf, *cy = b[4].buf, *cz = b[5].buf, *sx = b[6].buf, *sy = b[7].buf, *sz = b[8].buf;
    double *o = b[9].buf;
    float *start = b[10].buf;
    for (Py_ssize_t i = 0; i < n; ++i) {
        const double qx = x[i] - t[0] * s[i], qy = y[i] - t[1] * s[i], qz = z[i] - t[2] * s[i];
        const double ux = cz[i] * qx + sz[i] * qy, uy = -sz[i] * qx + cz[i] * qy;
        const double vy = cx[i] * uy + sx[i] * qz, vz = -sx[i] * uy + cx[i] * qz;
        o[i] = cx[i];
        o[n + i] = sx[i];
        o[2 * n + i] = cy[i];
        o[3 * n + i] = sy[i];
        o[4 * n + i] = cz[i];
        o[5 * n + i] = sz[i];
        o[6 * n + i] = s[i];
        o[7 * n + i] = qx;
        o[8 * n + i] = qy;
        o[9 * n + i] = qz;
        o[10 * n + i] = ux;
        o[11 * n + i] = uy;
        o[12 * n + i] = vz;
        o[13 * n + i] = vy;
        start[3 * i] = (float)(cy[i] * ux - sy[i] * vz);
        start[3 * i + 1] = (float)vy;
        start[3 * i + 2] = (float)(sy[i] * ux + cy[i] * vz);
    }
    result = Py_None;
    Py_INCREF(result);
done:
    for (int i = 0; i < 11; ++i) {
        if (b[i].obj != NULL) {
            PyBuffer_Release(&b[i]);
        }
    }
    return result;
}

/* One point of euler_rotate: left @ (Ry Rx Rz) @ p from the cosines and sines of (rx, ry, rz), written to out[0],
 * out[stride], out[2 * stride]. */
static inline void euler_point(const double *l, double cx, double cy, double cz, double sx, double sy, double sz,
                               const float *p, double *out, Py_ssize_t stride) {
    const double sy_sx = sy * sx, cy_sx = cy * sx;
    double e[3][3];
    e[0][0] = cy * cz + sy_sx * sz;
    e[0][1] = -cy * sz + sy_sx * cz;
    e[0][2] = sy * cx;
    e[1][0] = cx * sz;
    e[1][1] = cx * cz;
    e[1][2] = -sx;
    e[2][0] = -sy * cz + cy_sx * sz;
    e[2][1] = sy * sz + cy_sx * cz;
    e[2][2] = cy * cx;
    const double x = (double)p[0], y = (double)p[1], z = (double)p[2];
    for (int r = 0; r < 3; ++r) {
        double m[3];
        for (int k = 0; k < 3; ++k) {
            m[k] = l[3 * r] * e[0][k] + l[3 * r + 1] * e[1][k] + l[3 * r + 2] * e[2][k];
        }
        out[r * stride] = (m[0] * x + m[2] * z) + m[1] * y + 0.0;
    }
}

static PyObject *py_euler_rotate(PyObject *self, PyObject *args) {
    Py_buffer left_buffer, cos_buffer, sin_buffer, xyz, out;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*y*y*w*", &left_buffer, &cos_buffer, &sin_buffer, &xyz, &out)) {
        return NULL;
    }
    PyObject *result = NULL;
    Py_ssize_t n = cos_buffer.len / (3 * (Py_ssize_t)sizeof(double));
    Py_ssize_t columns = n > 0 ? xyz.len / (n * (Py_ssize_t)sizeof(float)) : 3;
    if (left_buffer.len != 9 * (Py_ssize_t)sizeof(double) || cos_buffer.len != n * 3 * (Py_ssize_t)sizeof(double) ||
        sin_buffer.len != cos_buffer.len || columns < 3 || xyz.len != n * columns * (Py_ssize_t)sizeof(float) ||
        out.len != cos_buffer.len) {
        PyErr_SetString(PyExc_ValueError, "euler_rotate: inconsistent buffer sizes");
        goto done;
    }
    const double *l = left_buffer.buf, *c = cos_buffer.buf, *sn = sin_buffer.buf;
    const float *p = xyz.buf;
    double *o = out.buf;
    for (Py_ssize_t i = 0; i < n; ++i) {
        euler_point(l, c[i], c[n + i], c[2 * n + i], sn[i], sn[n + i], sn[2 * n + i], p + columns * i, o + i, n);
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&left_buffer);
    PyBuffer_Release(&cos_buffer);
    PyBuffer_Release(&sin_buffer);
    PyBuffer_Release(&xyz);
    PyBuffer_Release(&out);
    return result;
}

/* NumPy's sort order for searchsorted: a < b, and NaN after every number. */
static inline int numpy_less(double a, double b) { return a < b || (b != b && a == a); }

/* np.minimum(t - newest, max_reach): NaN stays NaN. */
static inline double reach_beyond(double t, double newest, double max_reach) {
    const double ahead = t - newest;
    return ahead != ahead || ahead < max_reach ? ahead : max_reach;
}

/* searchsorted(side='left') of t in the table's times: the first row not before t. */
static inline int left_of(const double *rows, Py_ssize_t m, Py_ssize_t at, double t) {
    return (at == 0 || numpy_less(rows[13 * (at - 1)], t)) && (at == m || !numpy_less(rows[13 * at], t));
}

/* Whether imu_lerp carries the attitudes on: some time lies more than stamp_rounding beyond the newest sample. */
static int carries_on(const double *times, Py_ssize_t n, double newest, double max_reach, double stamp_rounding) {
    for (Py_ssize_t i = 0; i < n; ++i) {
        if (reach_beyond(times[i], newest, max_reach) > stamp_rounding) return 1;
    }
    return 0;
}

/* One time's roll, pitch and yaw (imu_lerp, see the file) into o[0..2]; *low is the bracket of the previous time,
 * tried first. With carried, the attitude is carried on as _carry_on's arrays do (to every row, zeros included). */
static inline void lerp_attitude(const double *rows, Py_ssize_t m, Py_ssize_t *low, double t, double max_reach,
                                 double stamp_rounding, int carried, const double *rate, double *o) {
    const double pi = 3.141592653589793, two_pi = 2 * 3.141592653589793;
    const double newest = rows[13 * (m - 1)];
    if (!left_of(rows, m, *low, t) && !(*low < m && left_of(rows, m, *low + 1, t))) {
        Py_ssize_t lo = 0, high = m;
        while (lo < high) {
            Py_ssize_t middle = lo + (high - lo) / 2;
            if (numpy_less(rows[13 * middle], t)) {
                lo = middle + 1;
            } else {
                high = middle;
            }
        }
        *low = lo;
    } else if (!left_of(rows, m, *low, t)) {
        ++*low;
    }
    Py_ssize_t front = *low > m - 1 ? m - 1 : *low;
    Py_ssize_t back = front - 1 > 0 ? front - 1 : 0;
    const double *rb = rows + 13 * back, *rf = rows + 13 * front;
    const double span = rf[0] - rb[0];
    double ratio = span > 0 ? (t - rb[0]) / span : 1.0;
    if (ratio == ratio) { /* clip to [0, 1] as NumPy does: NaN stays NaN, -0.0 stays -0.0 */
        ratio = 0.0 > ratio ? 0.0 : ratio;
        ratio = ratio > 1.0 ? 1.0 : ratio;
    }
    if (t >= newest) {
        ratio = 1.0;
    }
    o[0] = rb[1] + (rf[1] - rb[1]) * ratio;
    o[1] = rb[2] + (rf[2] - rb[2]) * ratio;
    const double jump = rf[3] - rb[3];
    const double unwrapped = rb[3] + (jump > pi ? two_pi : (jump < -pi ? -two_pi : 0.0));
    o[2] = unwrapped + (rf[3] - unwrapped) * ratio;
    if (carried) { /* rpy += where(ahead > rounding, ahead, 0.0)[:, None] * rate[None, :] */
        const double ahead = reach_beyond(t, newest, max_reach);
        const double factor = ahead > stamp_rounding ? ahead : 0.0;
        for (int c = 0; c < 3; ++c) {
            o[c] += factor * rate[c];
        }
    }
}

/* The rows m of imu_lerp's and imu_rotate_at's table and the times n, their buffers checked with the rate's: 1, or
 * 0 with a ValueError naming the function. */
static int attitude_sizes(const Py_buffer *table, const Py_buffer *times, const Py_buffer *rate, const char *function,
                          Py_ssize_t *m, Py_ssize_t *n) {
    *m = table->len / (13 * (Py_ssize_t)sizeof(double));
    *n = times->len / (Py_ssize_t)sizeof(double);
    if (*m < 1 || table->len != *m * 13 * (Py_ssize_t)sizeof(double) || times->len != *n * (Py_ssize_t)sizeof(double) ||
        rate->len != 3 * (Py_ssize_t)sizeof(double)) {
        PyErr_Format(PyExc_ValueError, "%s: inconsistent buffer sizes", function);
        return 0;
    }
    return 1;
}

static PyObject *py_imu_lerp(PyObject *self, PyObject *args) {
    Py_buffer table, times_buffer, out, rate_buffer;
    double max_reach, stamp_rounding;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*w*ddy*", &table, &times_buffer, &out, &max_reach, &stamp_rounding,
                          &rate_buffer)) {
        return NULL;
    }
    PyObject *result = NULL;
    Py_ssize_t m, n;
    if (!attitude_sizes(&table, &times_buffer, &rate_buffer, "imu_lerp", &m, &n)) goto done;
    if (out.len != n * 3 * (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, "imu_lerp: inconsistent buffer sizes");
        goto done;
    }
    const double *rows = table.buf, *times = times_buffer.buf;
    const int carried = carries_on(times, n, rows[13 * (m - 1)], max_reach, stamp_rounding);
    Py_ssize_t low = 0;
    for (Py_ssize_t i = 0; i < n; ++i) {
        lerp_attitude(rows, m, &low, times[i], max_reach, stamp_rounding, carried, rate_buffer.buf,
                      (double *)out.buf + 3 * i);
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&table);
    PyBuffer_Release(&times_buffer);
    PyBuffer_Release(&out);
    PyBuffer_Release(&rate_buffer);
    return result;
}

static PyObject *py_imu_rotate_at(PyObject *self, PyObject *args) {
    Py_buffer table, times_buffer, rate_buffer, left_buffer, xyz, out;
    double max_reach, stamp_rounding;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*ddy*y*y*w*", &table, &times_buffer, &max_reach, &stamp_rounding, &rate_buffer,
                          &left_buffer, &xyz, &out)) {
        return NULL;
    }
    PyObject *result = NULL;
    Py_ssize_t m, n;
    if (!attitude_sizes(&table, &times_buffer, &rate_buffer, "imu_rotate_at", &m, &n)) goto done;
    const Py_ssize_t columns = n > 0 ? xyz.len / (n * (Py_ssize_t)sizeof(float)) : 3;
    if (left_buffer.len != 9 * (Py_ssize_t)sizeof(double) || columns < 3 ||
        xyz.len != n * columns * (Py_ssize_t)sizeof(float) || out.len != 3 * n * (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, "imu_rotate_at: inconsistent buffer sizes");
        goto done;
    }
    const double *rows = table.buf, *times = times_buffer.buf, *rate = rate_buffer.buf, *l = left_buffer.buf;
    const float *p = xyz.buf;
    double *o = out.buf;
    Py_BEGIN_ALLOW_THREADS
    const int carried = carries_on(times, n, rows[13 * (m - 1)], max_reach, stamp_rounding);
    Py_ssize_t low = 0;
    for (Py_ssize_t i = 0; i < n; ++i) { /* imu_rotate's angles (rx, ry, rz) = (pitch, yaw, roll) */
        double rpy[3];
        lerp_attitude(rows, m, &low, times[i], max_reach, stamp_rounding, carried, rate, rpy);
        euler_point(l, cos(rpy[1]), cos(rpy[2]), cos(rpy[0]), sin(rpy[1]), sin(rpy[2]), sin(rpy[0]), p + columns * i,
                    o + i, n);
    }
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&table);
    PyBuffer_Release(&times_buffer);
    PyBuffer_Release(&rate_buffer);
    PyBuffer_Release(&left_buffer);
    PyBuffer_Release(&xyz);
    PyBuffer_Release(&out);
    return result;
}

static PyObject *py_occluded(PyObject *self, PyObject *args) {
    Py_buffer ranges, columns, picked;
    long long half_window;
    double column_gap, ratio;
    float jump;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*Ldfdw*", &ranges, &columns, &half_window, &column_gap, &jump, &ratio, &picked)) {
        return NULL;
    }
    PyObject *result = NULL;
    Py_ssize_t n = ranges.len / (Py_ssize_t)sizeof(float);
    if (ranges.len != n * (Py_ssize_t)sizeof(float) || columns.len != n * 8 || picked.len != n || half_window < 0) {
        PyErr_SetString(PyExc_ValueError, "occluded: inconsistent buffer sizes");
        goto done;
    }
    const float *r = ranges.buf;
    const int64_t *col = columns.buf;
    uint8_t *out = picked.buf;
    const int64_t w = half_window;
    for (int64_t i = w; i < (int64_t)n - w - 1; ++i) {
        const float d1 = r[i], d2 = r[i + 1];
        int64_t gap = col[i + 1] - col[i];
        gap = gap < 0 ? -gap : gap;
        if ((double)gap < column_gap) {
            if ((double)d1 - (double)d2 > (double)jump) { /* i is the far side: mark i - w .. i */
                memset(out + i - w, 1, (size_t)(w + 1));
            } else if ((double)d2 - (double)d1 > (double)jump) { /* mark i + 1 .. i + 1 + w */
                memset(out + i + 1, 1, (size_t)(w + 1));
            }
        }
        const float before = r[i >= 1 ? i - 1 : i - 1 + (int64_t)n]; /* (i - 1 wraps when w = 0, as indexing) */
        const float diff1 = fabsf(before - d1), diff2 = fabsf(d2 - d1);
        const double limit = ratio * (double)d1;
        if ((double)diff1 > limit && (double)diff2 > limit) {
            out[i] = 1;
        }
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&ranges);
    PyBuffer_Release(&columns);
    PyBuffer_Release(&picked);
    return result;
}

static PyObject *py_line_term(PyObject *self, PyObject *args) {
    Py_buffer b[9];
    int weighted;
    double gain, min_weight;
    long long start_columns, last_columns;
    (void)self;
    memset(b, 0, sizeof(b));
    if (!PyArg_ParseTuple(args, "y*Ly*Ly*y*pddw*w*w*w*w*", &b[0], &start_columns, &b[1], &last_columns, &b[2], &b[3],
                          &weighted, &gain, &min_weight, &b[4], &b[5], &b[6], &b[7], &b[8])) {
        return NULL;
    }
    PyObject *result = NULL;
    const Py_ssize_t n = b[2].len / 8, f = (Py_ssize_t)sizeof(float), d = (Py_ssize_t)sizeof(double);
    const Py_ssize_t m = last_columns >= 3 ? b[1].len / (last_columns * f) : -1;
    if (start_columns < 3 || last_columns < 3 || b[0].len != n * start_columns * f ||
        b[1].len != m * last_columns * f || b[2].len != n * 8 || b[3].len != n * 8 || b[4].len != n * 8 ||
        b[5].len != 3 * n * d || b[6].len != 3 * n * d || b[7].len != n * d || b[8].len != 9 * n * d) {
        PyErr_SetString(PyExc_ValueError, "line_term: inconsistent buffer sizes");
        goto done;
    }
    const float *start = b[0].buf, *last = b[1].buf;
    const int64_t *index1 = b[2].buf, *index2 = b[3].buf;
    int64_t *chosen = b[4].buf;
    double *anchor = b[5].buf, *along = b[6].buf, *weight = b[7].buf, *coeff = b[8].buf;
    Py_ssize_t kept = 0;
    for (Py_ssize_t i = 0; i < n; ++i) {
        if (index2[i] < 0) {
            continue;
        }
        if (index1[i] < 0 || index1[i] >= m || index2[i] >= m) {
            PyErr_SetString(PyExc_IndexError, "line_term: a line point outside the last cloud");
            goto done;
        }
        const float *pa = last + index1[i] * last_columns, *pb = last + index2[i] * last_columns;
        const float *p = start + i * start_columns;
        const double a[3] = {pa[0], pa[1], pa[2]};
        const double diff[3] = {a[0] - (double)pb[0], a[1] - (double)pb[1], a[2] - (double)pb[2]};
        const double length = sqrt(diff[0] * diff[0] + diff[1] * diff[1] + diff[2] * diff[2]);
        const double u[3] = {diff[0] / length, diff[1] / length, diff[2] / length};
        const double q[3] = {(double)p[0] - a[0], (double)p[1] - a[1], (double)p[2] - a[2]};
        const double dot = (q[0] * u[0] + q[2] * u[2]) + q[1] * u[1];
        const double off[3] = {q[0] - dot * u[0], q[1] - dot * u[1], q[2] - dot * u[2]};
        const double distance = sqrt(off[0] * off[0] + off[1] * off[1] + off[2] * off[2]);
        const double w = weighted ? 1.0 - gain * fabs(distance) / 1.0 : 1.0; /* (/ 1.0: _term's scale of lines) */
        if (!(w > min_weight) || !isfinite(distance) || !isfinite(u[0]) || !isfinite(u[1]) || !isfinite(u[2])) {
            continue;
        }
        chosen[kept] = i;
        weight[kept] = w;
        for (int r = 0; r < 3; ++r) {
            anchor[3 * kept + r] = a[r];
            along[3 * kept + r] = u[r];
            for (int c = 0; c < 3; ++c) {
                coeff[9 * kept + 3 * r + c] = ((r == c ? 1.0 : 0.0) - u[r] * u[c]) * w;
            }
        }
        ++kept;
    }
    result = PyLong_FromSsize_t(kept);
done:
    for (int i = 0; i < 9; ++i) {
        if (b[i].obj != NULL) {
            PyBuffer_Release(&b[i]);
        }
    }
    return result;
}

/* out = a @ b for row-major 3x3 matrices, each entry summed over k = 0, 1, 2 in that order (gyro.py's _product). */
static void product3(const double *a, const double *b, double *out) {
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) {
            out[3 * i + j] = a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j];
        }
    }
}

/* gyro.py's _exp: Rodrigues, the rotation of the rotation vector (vx, vy, vz). */
static void rotation_of_vector(double vx, double vy, double vz, double *out) {
    static const double identity[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
    const double angle = sqrt(vx * vx + vy * vy + vz * vz);
    if (angle < 1e-12) {
        memcpy(out, identity, sizeof(identity));
        return;
    }
    const double kx = vx / angle, ky = vy / angle, kz = vz / angle;
    const double cross[9] = {0.0, -kz, ky, kz, 0.0, -kx, -ky, kx, 0.0};
    double square[9];
    product3(cross, cross, square);
    const double sine = sin(angle), versine = 1.0 - cos(angle);
    for (int i = 0; i < 9; ++i) {
        out[i] = identity[i] + sine * cross[i] + versine * square[i];
    }
}

/* gyro.py's matrix_of_rpy: Rz(yaw) Ry(pitch) Rx(roll), row-major. */
static void matrix_of_rpy(double roll, double pitch, double yaw, double *out) {
    const double cr = cos(roll), sr = sin(roll), cp = cos(pitch), sp = sin(pitch), cy = cos(yaw), sy = sin(yaw);
    out[0] = cy * cp;
    out[1] = cy * sp * sr - sy * cr;
    out[2] = cy * sp * cr + sy * sr;
    out[3] = sy * cp;
    out[4] = sy * sp * sr + cy * cr;
    out[5] = sy * sp * cr - cy * sr;
    out[6] = -sp;
    out[7] = cp * sr;
    out[8] = cp * cr;
}

static inline double clamp_unit(double value) { /* Python's max(-1.0, min(1.0, value)), NaN included */
    const double low = value < 1.0 ? value : 1.0;
    return low > -1.0 ? low : -1.0;
}

static int read_numbers(PyObject *sequence, double *out, Py_ssize_t count) {
    PyObject *fast = PySequence_Fast(sequence, "a sequence of numbers");
    if (fast == NULL) {
        return -1;
    }
    int status = PySequence_Fast_GET_SIZE(fast) == count ? 0 : -1;
    for (Py_ssize_t i = 0; i < count && status == 0; ++i) {
        out[i] = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(fast, i));
        if (out[i] == -1.0 && PyErr_Occurred()) {
            status = -1;
        }
    }
    Py_DECREF(fast);
    if (status < 0 && !PyErr_Occurred()) {
        PyErr_SetString(PyExc_ValueError, "imu_sample: a sequence of the wrong length");
    }
    return status;
}

static PyObject *py_imu_sample(PyObject *self, PyObject *args) {
    double stamp, offset, reset_after, period, gravity, tolerance, max_rate, max_acceleration;
    PyObject *orientation, *rate_sequence, *acceleration, *last_row, *state_object, *bias_object;
    (void)self;
    if (!PyArg_ParseTuple(args, "dOOOOdddddddOO", &stamp, &orientation, &rate_sequence, &acceleration, &last_row,
                          &offset, &reset_after, &period, &gravity, &tolerance, &max_rate, &max_acceleration,
                          &state_object, &bias_object)) {
        return NULL;
    }
    double q[4], g[3], a[3], last[13];
    if (read_numbers(orientation, q, 4) < 0 || read_numbers(rate_sequence, g, 3) < 0 ||
        read_numbers(acceleration, a, 3) < 0) {
        return NULL;
    }
    const int has_last = last_row != Py_None;
    if (has_last && read_numbers(last_row, last, 13) < 0) {
        return NULL;
    }
    /* The checks of ImuBuffer.add, in its order; any failing one: None (the Python code says why). */
    int finite = isfinite(stamp);
    for (int i = 0; i < 4; ++i) {
        finite = finite && isfinite(q[i]);
    }
    for (int i = 0; i < 3; ++i) {
        finite = finite && isfinite(g[i]) && isfinite(a[i]);
    }
    if (!finite) {
        Py_RETURN_NONE;
    }
    double scale = fabs(q[0]);
    for (int i = 1; i < 4; ++i) {
        scale = fabs(q[i]) > scale ? fabs(q[i]) : scale;
    }
    /* Python's x ** 2 is libm's pow(x, 2.0), which may differ from x * x in the last bit: the exponent is read
     * through a volatile so that the compiler does not turn the call into that product. */
    volatile double two = 2.0;
    const double norm = scale > 0 ? scale * sqrt(pow(q[0] / scale, two) + pow(q[1] / scale, two) +
                                                 pow(q[2] / scale, two) + pow(q[3] / scale, two))
                                   : 0.0;
    double largest_rate = fabs(g[0]), largest_acceleration = fabs(a[0]);
    for (int i = 1; i < 3; ++i) {
        largest_rate = fabs(g[i]) > largest_rate ? fabs(g[i]) : largest_rate;
        largest_acceleration = fabs(a[i]) > largest_acceleration ? fabs(a[i]) : largest_acceleration;
    }
    if (norm < 1e-6 || fabs(norm - 1.0) > tolerance || largest_rate > max_rate ||
        largest_acceleration > max_acceleration) {
        Py_RETURN_NONE;
    }
    if (offset != 0.0) {
        stamp -= offset;
    }
    if (has_last && (stamp < last[0] - reset_after || stamp <= last[0])) {
        Py_RETURN_NONE;
    }
    Py_buffer state = {0}, bias = {0};
    if (state_object != Py_None) {
        if (PyObject_GetBuffer(state_object, &state, PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS) < 0) {
            return NULL;
        }
        if (PyObject_GetBuffer(bias_object, &bias, PyBUF_C_CONTIGUOUS) < 0) {
            PyBuffer_Release(&state);
            return NULL;
        }
        if (state.len != 13 * (Py_ssize_t)sizeof(double) || bias.len != 3 * (Py_ssize_t)sizeof(double)) {
            PyBuffer_Release(&state);
            PyBuffer_Release(&bias);
            PyErr_SetString(PyExc_ValueError, "imu_sample: the gyro state holds 13 float64, its bias 3");
            return NULL;
        }
    }
    const double qx = q[0] / norm, qy = q[1] / norm, qz = q[2] / norm, qw = q[3] / norm;
    const double roll = atan2(2.0 * (qw * qx + qy * qz), 1.0 - 2.0 * (qx * qx + qy * qy));
    const double pitch = asin(clamp_unit(2.0 * (qw * qy - qz * qx)));
    const double yaw = atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz));
    double attitude[3] = {roll, pitch, yaw};
    const int following = has_last && stamp - last[0] < period;
    if (state.buf != NULL) { /* GyroAttitude.update */
        double *st = state.buf;
        const double *b = bias.buf;
        const double rx = g[0] - b[0], ry = g[1] - b[1], rz = g[2] - b[2];
        double matrix[9];
        if (!following || st[12] == 0.0) {
            matrix_of_rpy(roll, pitch, yaw, matrix);
        } else {
            const double dt = stamp - last[0];
            double step[9];
            rotation_of_vector(0.5 * (st[9] + rx) * dt, 0.5 * (st[10] + ry) * dt, 0.5 * (st[11] + rz) * dt, step);
            product3(st, step, matrix);
        }
        memcpy(st, matrix, sizeof(matrix));
        st[9] = rx;
        st[10] = ry;
        st[11] = rz;
        st[12] = 1.0;
        attitude[0] = atan2(matrix[7], matrix[8]);
        attitude[1] = asin(clamp_unit(-matrix[6]));
        attitude[2] = atan2(matrix[3], matrix[0]);
        PyBuffer_Release(&state);
        PyBuffer_Release(&bias);
    }
    /* Gravity-free acceleration in the body frame, in camera axes, then in the world (ImuBuffer.add). */
    const double cr = cos(roll), sr = sin(roll), cp = cos(pitch), sp = sin(pitch), cy = cos(yaw), sy = sin(yaw);
    const double bx = a[1] - sr * cp * gravity, by = a[2] - cr * cp * gravity, bz = a[0] + sp * gravity;
    const double world[3] = {
        (cy * cr + sy * sp * sr) * bx + (-cy * sr + sy * sp * cr) * by + sy * cp * bz,
        cp * sr * bx + cp * cr * by - sp * bz,
        (-sy * cr + cy * sp * sr) * bx + (sy * sr + cy * sp * cr) * by + cy * cp * bz,
    };
    double row[13] = {stamp, attitude[0], attitude[1], attitude[2], 0, 0, 0, 0, 0, 0, 0, 0, 0};
    if (following) {
        const double dt = stamp - last[0];
        for (int k = 0; k < 3; ++k) {
            row[4 + k] = last[4 + k] + world[k] * dt;
            row[7 + k] = last[7 + k] + last[4 + k] * dt + world[k] * dt * dt / 2;
            row[10 + k] = last[10 + k] + g[k] * dt;
        }
    } else if (has_last) { /* after a gap: the velocity starts again from 0, the integrals carry on */
        for (int k = 0; k < 3; ++k) {
            row[7 + k] = last[7 + k];
            row[10 + k] = last[10 + k];
        }
    }
    PyObject *result = PyTuple_New(13);
    if (result == NULL) {
        return NULL;
    }
    for (int i = 0; i < 13; ++i) {
        PyObject *value = PyFloat_FromDouble(row[i]);
        if (value == NULL) {
            Py_DECREF(result);
            return NULL;
        }
        PyTuple_SET_ITEM(result, i, value);
    }
    return result;
}

static PyMethodDef methods[] = {
    {"select_features", py_select_features, METH_VARARGS,
     "The greedy edge and flat selection of every sub-region (see the file)."},
    {"nearest_in_segments", py_nearest_in_segments, METH_VARARGS, "The nearest point of every window segment."},
    {"nearest_in_windows", py_nearest_in_windows, METH_VARARGS, "The window search of a ring-ordered cloud."},
    {"sweep_rows", py_sweep_rows, METH_VARARGS, "SweepStartFrame.rows in one pass."},
    {"sweep_frame", py_sweep_frame, METH_VARARGS, "SweepStartFrame's products and start points in one pass."},
    {"euler_rotate", py_euler_rotate, METH_VARARGS, "rotate_by_euler after its sines and cosines."},
    {"imu_lerp", py_imu_lerp, METH_VARARGS, "The IMU attitude interpolated at given times."},
    {"occluded", py_occluded, METH_VARARGS, "features.occluded_mask in one pass."},
    {"imu_sample", py_imu_sample, METH_VARARGS, "ImuBuffer.add's common case (see the file)."},
    {"imu_rotate_at", py_imu_rotate_at, METH_VARARGS, "imu_rotate at the IMU attitude of each time (see the file)."},
    {"line_term", py_line_term, METH_VARARGS, "The sweep-start odometry's line terms (see the file)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_feature_kernels", NULL, -1, methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__feature_kernels(void) { return PyModule_Create(&module); }
