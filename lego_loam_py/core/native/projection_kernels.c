/*
 * imageProjection's loops, in C: those NumPy cannot express, and passes fused where NumPy would make many. Each
 * module that calls one keeps its NumPy version for when this extension is not built, and the tests compare the
 * two (tests/test_projection_kernels.py, test_image_projection.py, test_laser_order.py). The kernels that run on
 * the offline runner's projection thread release the GIL.
 *
 * ground_walk(x, y, z, top, columns, ground, far, on_plane, slope, tolerance)
 *   GroundRemoval._refine_ground's walk up the columns (core/projection/ground.py), every column one row at a time
 *   as there, with its float64 operations in its order (built with -ffp-contract=off): x, y, z (top, columns)
 *   float32 coordinates, taken as float64 (exactly); ground, far and on_plane (top, columns) bool (ground rewritten
 *   in place). In each column, from the lowest row up, a ground candidate is kept when the column has no kept
 *   point yet and it is on the plane, or when |z - z_last| <= hypot(x - x_last, y - y_last) * slope + tolerance
 *   and it is on the plane or far; a kept point becomes the column's last. Runs without the GIL.
 *
 * segment_labels(range, candidate, rows, columns, row_sin, row_cos, column_sin, column_cos, theta, directions,
 *                min_cluster, valid_points, valid_lines, labels) -> segments
 *   Segmentation.labels (core/projection/segmentation.py), the original's breadth-first segmentation: the
 *   candidate pixels (uint8, non-ground and filled) of a (rows, columns) float32 range image joined to their
 *   4-neighbours (columns wrap around) where beta > theta, beta = atan2f(d2 sin(alpha), d1 - d2 cos(alpha)), d1 and
 *   d2 the larger and smaller range, alpha the angle between the two rows (row_sin / row_cos[r] for rows r and
 *   r + 1) or columns. Each decision is parity.atan2f_exceeds's, the same float32 operations: the signs of the
 *   cross products with the directions (cos, sin) just below and above theta in directions (float32 low_cos,
 *   low_sin, high_cos, high_sin; empty: libm's atan2f throughout) beyond their rounding bound, else libm's angle.
 *   A cluster is kept with at least min_cluster pixels, or valid_points over valid_lines rows (the rows of its
 *   pixels other than the first); kept clusters are numbered 1, 2, ... in the row-major order of their first
 *   pixel, the others labelled 999999, every other pixel -1 (labels, int32). Returns the number of clusters
 *   kept. Runs without the GIL.
 *
 * vertical_pairs(dx, dy, dz, x, y, filled, rows, columns, ratio, max_gap, ground)
 *   GroundRemoval._refine_ground's vertical pairs: the pixel (r, c) and the one above it, both filled (uint8), are
 *   a vertical pair where |dz| > ratio * gap and gap < max_gap * reach (float32), gap and reach the float32 hypot
 *   of (dx, dy) and of (x, y) as ground.float32_hypot takes them, (float) sqrt((double) a * a + (double) b * b);
 *   dx, dy, dz (rows - 1, columns) the steps to the row above, x, y and filled (at least rows, columns). Both
 *   pixels of a vertical pair are taken out of ground (rows, columns, uint8, in place).
 *
 * range_image(x, y, z, row, col, min_range, n_scan, columns, pixel_intensity, time, winner, range, full_info, full,
 *             pixel_time) -> (outside, close, kept, filled)
 *   RangeImageProjection.project's pass (core/projection/range_image.py): each point's float32 range
 *   sqrtf(x * x + y * y + z * z); the points with a row and column (int64, -1 outside the image) and a range of at
 *   least min_range go to their pixel, the last one of a pixel (the largest index) winning. Writes per pixel
 *   (n_scan * columns, row-major) the winner (int64, -1 empty), its range (FLT_MAX empty), its x y z range (full_info)
 *   and x y z pixel_intensity (full) (NaN NaN NaN -1 empty), and with a time per point (float32; an empty buffer
 *   for none) its time (0 empty). Returns the points outside the image, those in it too close (or NaN), those
 *   placed, and the pixels filled. Runs without the GIL.
 *
 * The laser order's passes over a cloud's points (core/projection/laser_order.py, which keeps their NumPy versions
 * for when this extension is not built; tests/test_laser_order.py compares the two), float64 throughout, each
 * operation the one NumPy does in its order. A kernel that meets a value NumPy's fast path would not take (NaN, a
 * value outside the fast range of the remainder) returns its "not here" answer and the caller takes NumPy's path:
 * abs_median(values) -> float or None
 *   np.median(np.abs(values)); None for NaN and for a zero middle value (whose sign is np.median's choice).
 * restarts(turned, cut, half_spacing, restart, begins) -> count
 *   with from_cut[i] = mod((turned[i] - cut) + half_spacing, 360) (the caller checked the range), the indices i
 *   where from_cut[i] - from_cut[i - 1] < -restart, written to begins (int64, n - 1 at most); returns how many.
 * elevation_steps(elevation, bound, falling, decided, starts) -> count or -1
 *   the indices i + 1 where elevation[i + 1] - elevation[i] < bound (falling) or > bound (rising), written to
 *   starts; with decided > 0, -1 as soon as a difference lies within decided of the bound (or is NaN).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>
#if defined(__SSE2__)
#include <emmintrin.h>
#endif

/* |dz| <= hypot(dx, dy) * slope + tolerance, with libm's hypot, whose call costs several times the rest: the
   horizontal gap is first taken as sqrt(dx * dx + dy * dy), within 3 ulps of hypot's for steps between float32
   coordinates (the squares and their sum are rounded once each and cannot overflow or underflow in float64); hypot
   is called only when that leaves the comparison within a margin far above those ulps, or the gap is not finite. */
static inline int rises_within(double dx, double dy, double dz, double slope, double tolerance) {
    const double rise = fabs(dz);
    double gap = sqrt(dx * dx + dy * dy);
    if (isfinite(gap) && slope >= 0.0) {
        double step = gap * slope;
        const double scale = step + fabs(tolerance) + rise; /* (bounds every term the comparison adds) */
        step += tolerance;
        if (fabs(rise - step) > 1e-12 * scale) return rise <= step;
    }
    gap = hypot(dx, dy);
    gap *= slope;
    gap += tolerance;
    return rise <= gap;
}

static PyObject *py_ground_walk(PyObject *self, PyObject *args) {
    Py_buffer xs, ys, zs, ground, far, on_plane;
    Py_ssize_t top, columns;
    double slope, tolerance;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*y*nnw*y*y*dd", &xs, &ys, &zs, &top, &columns, &ground, &far, &on_plane, &slope,
                          &tolerance)) {
        return NULL;
    }
    PyObject *result = NULL;
    const Py_ssize_t cells = top * columns, bytes = cells * (Py_ssize_t)sizeof(float);
    if (top < 0 || columns < 0 || xs.len != bytes || ys.len != bytes || zs.len != bytes || ground.len != cells ||
        far.len != cells || on_plane.len != cells) {
        PyErr_SetString(PyExc_ValueError, "ground_walk: inconsistent buffer sizes");
        goto done;
    }
    const float *x = xs.buf, *y = ys.buf, *z = zs.buf;
    uint8_t *keep = ground.buf;
    const uint8_t *is_far = far.buf, *planar = on_plane.buf;
    /* Row by row, each column's walk one step at a time: the columns' steps are independent of each other (they
       overlap in the pipeline and read the rows in memory order), each column's in the order of its rows. */
    double *last = malloc((size_t)(3 * columns + 1) * sizeof(double));
    uint8_t *seeded = calloc((size_t)columns + 1, 1);
    if (last == NULL || seeded == NULL) {
        free(last);
        free(seeded);
        PyErr_NoMemory();
        goto done;
    }
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t r = 0; r < top; ++r) {
        for (Py_ssize_t c = 0; c < columns; ++c) {
            const Py_ssize_t i = r * columns + c;
            if (!keep[i]) continue;
            const double px = x[i], py = y[i], pz = z[i];
            double *before = last + 3 * c;
            int accepted;
            if (!seeded[c]) {
                accepted = planar[i] != 0;
            } else {
                accepted = (is_far[i] || planar[i]) &&
                           rises_within(px - before[0], py - before[1], pz - before[2], slope, tolerance);
            }
            keep[i] = (uint8_t)accepted;
            if (accepted) {
                before[0] = px;
                before[1] = py;
                before[2] = pz;
                seeded[c] = 1;
            }
        }
    }
    Py_END_ALLOW_THREADS
    free(last);
    free(seeded);
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&xs);
    PyBuffer_Release(&ys);
    PyBuffer_Release(&zs);
    PyBuffer_Release(&ground);
    PyBuffer_Release(&far);
    PyBuffer_Release(&on_plane);
    return result;
}


/* Whether neighbours at ranges a[i] and b[i], sin_alpha and cos_alpha apart, join: beta > theta, decided as
   parity.atan2f_exceeds decides it (see the top of the file), for count pairs into joined (0 or 1). The cross
   products in a branch-free, vectorised pass (int32 lanes as wide as the floats', 2 where neither decides), then
   libm's angle for the few left. A NaN range gives no join (NaN cross products decide "not above"), as there. */
static void join_pairs(const float *a, const float *b, Py_ssize_t count, float sin_alpha, float cos_alpha, float theta,
                       const float *directions, int all_libm, int32_t *decision, uint8_t *joined) {
    if (!all_libm) {
        const float low_cos = directions[0], low_sin = directions[1], high_cos = directions[2],
                    high_sin = directions[3];
        for (Py_ssize_t i = 0; i < count; ++i) {
            const float larger = a[i] > b[i] ? a[i] : b[i], smaller = a[i] > b[i] ? b[i] : a[i];
            const float y = smaller * sin_alpha, x = larger - smaller * cos_alpha;
            const float bound = (fabsf(y) + fabsf(x)) * 0x1p-21f + 0x1p-120f;
            const int32_t above = y * high_cos - x * high_sin > bound;
            /* "not >= -bound" rather than "< -bound": NaN (no angle) is never above, as in libm. */
            const int32_t not_above = !(y * low_cos - x * low_sin >= -bound);
            decision[i] = above | ((above | not_above) ^ 1) << 1;
        }
    }
    for (Py_ssize_t i = 0; i < count; ++i) {
        if (all_libm || decision[i] == 2) {
            const float larger = a[i] > b[i] ? a[i] : b[i], smaller = a[i] > b[i] ? b[i] : a[i];
            joined[i] = atan2f(smaller * sin_alpha, larger - smaller * cos_alpha) > theta;
        } else {
            joined[i] = (uint8_t)decision[i];
        }
    }
}

static PyObject *py_segment_labels(PyObject *self, PyObject *args) {
    Py_buffer ranges, candidates, row_sins, row_coses, direction_buffer, label_buffer;
    Py_ssize_t rows, columns, min_cluster, valid_points, valid_lines;
    float column_sin, column_cos, theta;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*nny*y*fffy*nnnw*", &ranges, &candidates, &rows, &columns, &row_sins, &row_coses,
                          &column_sin, &column_cos, &theta, &direction_buffer, &min_cluster, &valid_points,
                          &valid_lines, &label_buffer)) {
        return NULL;
    }
    PyObject *result = NULL;
    const Py_ssize_t f = (Py_ssize_t)sizeof(float), pixels = rows * columns;
    if (rows < 1 || columns < 1 || ranges.len != pixels * f || candidates.len != pixels ||
        row_sins.len != (rows - 1) * f || row_coses.len != row_sins.len ||
        (direction_buffer.len != 0 && direction_buffer.len != 4 * f) || label_buffer.len != pixels * 4) {
        PyErr_SetString(PyExc_ValueError, "segment_labels: inconsistent buffer sizes");
        goto done;
    }
    const float *range = ranges.buf, *row_sin = row_sins.buf, *row_cos = row_coses.buf;
    const float *directions = direction_buffer.buf;
    const int all_libm = direction_buffer.len == 0;
    const uint8_t *candidate = candidates.buf;
    int32_t *label = label_buffer.buf;
    /* joined_up[p]: p and the pixel above it; joined_right[p]: p and the next column's (the last wraps), both
       candidates. */
    uint8_t *joined_up = malloc((size_t)pixels), *joined_right = malloc((size_t)pixels);
    uint8_t *line_seen = malloc((size_t)rows);
    int32_t *decision = malloc((size_t)columns * sizeof(int32_t));
    Py_ssize_t *queue = malloc((size_t)pixels * sizeof(Py_ssize_t));
    Py_ssize_t *queue_row = malloc((size_t)pixels * sizeof(Py_ssize_t)); /* (the row of each: no division) */
    int64_t kept = 0;
    if (!joined_up || !joined_right || !line_seen || !decision || !queue || !queue_row) {
        free(joined_up);
        free(joined_right);
        free(line_seen);
        free(decision);
        free(queue);
        free(queue_row);
        PyErr_NoMemory();
        goto done;
    }
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t r = 0; r < rows; ++r) {
        const float *here = range + r * columns;
        const Py_ssize_t first = r * columns;
        join_pairs(here, here + 1, columns - 1, column_sin, column_cos, theta, directions, all_libm, decision,
                   joined_right + first);
        join_pairs(here + columns - 1, here, 1, column_sin, column_cos, theta, directions, all_libm, decision,
                   joined_right + first + columns - 1); /* (the last column and the first) */
        if (r + 1 < rows) {
            join_pairs(here, here + columns, columns, row_sin[r], row_cos[r], theta, directions, all_libm, decision,
                       joined_up + first);
        } else {
            memset(joined_up + first, 0, (size_t)columns);
        }
        for (Py_ssize_t c = 0; c < columns; ++c) {
            const Py_ssize_t p = first + c;
            joined_right[p] &= candidate[p] & candidate[c + 1 < columns ? p + 1 : first];
            if (r + 1 < rows) joined_up[p] &= candidate[p] & candidate[p + columns];
        }
    }
    for (Py_ssize_t p = 0; p < pixels; ++p) label[p] = candidate[p] ? 0 : -1;
    int32_t number = 1;
    for (Py_ssize_t seed = 0; seed < pixels; ++seed) {
        if (label[seed] != 0) continue;
        Py_ssize_t head = 0, tail = 0, lines = 0;
        memset(line_seen, 0, (size_t)rows);
        queue[tail] = seed;
        queue_row[tail++] = seed / columns;
        label[seed] = number;
        while (head < tail) {
            const Py_ssize_t p = queue[head], r = queue_row[head++], c = p - r * columns;
            const Py_ssize_t left = c > 0 ? p - 1 : p + columns - 1, right = c + 1 < columns ? p + 1 : p - c;
            const Py_ssize_t neighbour[4] = {r > 0 ? p - columns : -1, right, left, r + 1 < rows ? p + columns : -1};
            const Py_ssize_t neighbour_row[4] = {r - 1, r, r, r + 1};
            const uint8_t joined[4] = {r > 0 && joined_up[p - columns], joined_right[p], joined_right[left],
                                       joined_up[p]};
            for (int k = 0; k < 4; ++k) {
                const Py_ssize_t q = neighbour[k];
                if (!joined[k] || label[q] != 0) continue;
                label[q] = number;
                queue[tail] = q;
                queue_row[tail++] = neighbour_row[k];
                if (!line_seen[neighbour_row[k]]) {
                    line_seen[neighbour_row[k]] = 1;
                    ++lines;
                }
            }
        }
        if (tail >= min_cluster || (tail >= valid_points && lines >= valid_lines)) {
            ++number;
            ++kept;
        } else {
            for (Py_ssize_t k = 0; k < tail; ++k) label[queue[k]] = 999999;
        }
    }
    Py_END_ALLOW_THREADS
    free(joined_up);
    free(joined_right);
    free(line_seen);
    free(decision);
    free(queue);
    free(queue_row);
    result = PyLong_FromLongLong(kept);
done:
    PyBuffer_Release(&ranges);
    PyBuffer_Release(&candidates);
    PyBuffer_Release(&row_sins);
    PyBuffer_Release(&row_coses);
    PyBuffer_Release(&direction_buffer);
    PyBuffer_Release(&label_buffer);
    return result;
}

static inline float hypot_of_floats(float a, float b) {
    return (float)sqrt((double)a * a + (double)b * b);
}

static PyObject *py_vertical_pairs(PyObject *self, PyObject *args) {
    Py_buffer dxs, dys, dzs, xs, ys, filled, grounds;
    Py_ssize_t rows, columns;
    float ratio, max_gap;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*nnffw*", &dxs, &dys, &dzs, &xs, &ys, &filled, &rows, &columns, &ratio,
                          &max_gap, &grounds)) {
        return NULL;
    }
    PyObject *result = NULL;
    const Py_ssize_t f = (Py_ssize_t)sizeof(float), pairs = (rows - 1) * columns, cells = rows * columns;
    if (rows < 1 || columns < 0 || dxs.len != pairs * f || dys.len != dxs.len || dzs.len != dxs.len ||
        xs.len < pairs * f || ys.len < pairs * f || filled.len < cells || grounds.len != cells) {
        PyErr_SetString(PyExc_ValueError, "vertical_pairs: inconsistent buffer sizes");
        goto done;
    }
    const float *dx = dxs.buf, *dy = dys.buf, *dz = dzs.buf, *x = xs.buf, *y = ys.buf;
    const uint8_t *full = filled.buf;
    uint8_t *ground = grounds.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < pairs; ++i) {
        if (!(full[i] && full[i + columns])) continue;
        const float gap = hypot_of_floats(dx[i], dy[i]), rise = fabsf(dz[i]);
        if (rise > ratio * gap && gap < max_gap * hypot_of_floats(x[i], y[i])) {
            ground[i] = 0;
            ground[i + columns] = 0;
        }
    }
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&dxs);
    PyBuffer_Release(&dys);
    PyBuffer_Release(&dzs);
    PyBuffer_Release(&xs);
    PyBuffer_Release(&ys);
    PyBuffer_Release(&filled);
    PyBuffer_Release(&grounds);
    return result;
}

static PyObject *py_range_image(PyObject *self, PyObject *args) {
    Py_buffer xs, ys, zs, rows, cols, intensity, times, winners, ranges, infos, fulls, pixel_times;
    float min_range;
    Py_ssize_t n_scan, columns;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*fnny*y*w*w*w*w*w*", &xs, &ys, &zs, &rows, &cols, &min_range, &n_scan,
                          &columns, &intensity, &times, &winners, &ranges, &infos, &fulls, &pixel_times)) {
        return NULL;
    }
    PyObject *result = NULL;
    const Py_ssize_t n = xs.len / (Py_ssize_t)sizeof(float), pixels = n_scan * columns;
    const Py_ssize_t f = (Py_ssize_t)sizeof(float);
    const int timed = times.len > 0;
    if (n_scan < 0 || columns < 0 || xs.len != n * f || ys.len != xs.len || zs.len != xs.len || rows.len != n * 8 ||
        cols.len != n * 8 || intensity.len != pixels * f || winners.len != pixels * 8 || ranges.len != pixels * f ||
        infos.len != 4 * pixels * f || fulls.len != infos.len || (timed && times.len != n * f) ||
        pixel_times.len != (timed ? pixels * f : 0)) {
        PyErr_SetString(PyExc_ValueError, "range_image: inconsistent buffer sizes");
        goto done;
    }
    const float *x = xs.buf, *y = ys.buf, *z = zs.buf, *pixel_intensity = intensity.buf, *time = times.buf;
    const int64_t *row = rows.buf, *col = cols.buf;
    int64_t *winner = winners.buf;
    float *range = ranges.buf, *info = infos.buf, *full = fulls.buf, *pixel_time = pixel_times.buf;
    long long outside = 0, close = 0, kept = 0, filled = 0;
    int bad = 0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t p = 0; p < pixels; ++p) winner[p] = -1;
    for (Py_ssize_t i = 0; i < n; ++i) {
        if (row[i] < 0 || col[i] < 0) {
            ++outside;
            continue;
        }
        if (row[i] >= n_scan || col[i] >= columns) {
            bad = 1;
            break;
        }
        const float r = sqrtf(x[i] * x[i] + y[i] * y[i] + z[i] * z[i]);
        if (!(r >= min_range)) {
            ++close;
            continue;
        }
        ++kept;
        winner[row[i] * columns + col[i]] = i;
    }
    if (!bad) {
        for (Py_ssize_t p = 0; p < pixels; ++p) {
            const int64_t w = winner[p];
            float *cell = info + 4 * p, *shown = full + 4 * p;
            if (w >= 0) {
                ++filled;
                const float r = sqrtf(x[w] * x[w] + y[w] * y[w] + z[w] * z[w]);
                cell[0] = shown[0] = x[w];
                cell[1] = shown[1] = y[w];
                cell[2] = shown[2] = z[w];
                cell[3] = r;
                shown[3] = pixel_intensity[p];
                range[p] = r;
                if (timed) pixel_time[p] = time[w];
            } else {
                cell[0] = cell[1] = cell[2] = shown[0] = shown[1] = shown[2] = NAN;
                cell[3] = shown[3] = -1.0f; /* an empty pixel's intensity is -1 in both clouds */
                range[p] = FLT_MAX;
                if (timed) pixel_time[p] = 0.0f;
            }
        }
    }
    Py_END_ALLOW_THREADS
    if (bad) {
        PyErr_SetString(PyExc_IndexError, "range_image: a row or column beyond the image");
        goto done;
    }
    result = Py_BuildValue("(LLLL)", outside, close, kept, filled);
done:
    PyBuffer_Release(&xs);
    PyBuffer_Release(&ys);
    PyBuffer_Release(&zs);
    PyBuffer_Release(&rows);
    PyBuffer_Release(&cols);
    PyBuffer_Release(&intensity);
    PyBuffer_Release(&times);
    PyBuffer_Release(&winners);
    PyBuffer_Release(&ranges);
    PyBuffer_Release(&infos);
    PyBuffer_Release(&fulls);
    PyBuffer_Release(&pixel_times);
    return result;
}

/* The laser order's kernels (see the top of the file).

   Rearranges a[0..n) so that a[k] holds the value of rank k, no greater value before it and no smaller one after
   (Wirth's selection: partitions around the value at k until the part holding k is that value alone). */
static double select_rank(double *a, Py_ssize_t n, Py_ssize_t k) {
    Py_ssize_t low = 0, high = n - 1;
    while (low < high) {
        const double pivot = a[k];
        Py_ssize_t i = low, j = high;
        do {
            while (a[i] < pivot) ++i;
            while (pivot < a[j]) --j;
            if (i <= j) {
                const double t = a[i];
                a[i] = a[j];
                a[j] = t;
                ++i;
                --j;
            }
        } while (i <= j);
        if (j < k) low = i;
        if (k < i) high = j;
    }
    return a[k];
}

static int compare_doubles(const void *p, const void *q) {
    const double a = *(const double *)p, b = *(const double *)q;
    return (a > b) - (a < b);
}

/* The value of rank k (and, with below_too, the one of rank k - 1) of the n values v (no NaN), rearranged in place:
   the ranks are first looked for among the values between two bounds taken from a sorted sample (moved to the
   front), which hold them unless the values are spread unevenly; else among all. The answer is the same either
   way: order statistics are values. */
static void ranked(double *v, Py_ssize_t n, Py_ssize_t k, int below_too, double *at_k, double *before_k) {
    enum { SAMPLE = 512, MARGIN = 24 };
    Py_ssize_t count = n, offset = 0;
    if (n >= 8 * SAMPLE) {
        double sample[SAMPLE];
        const Py_ssize_t stride = n / SAMPLE;
        for (int s = 0; s < SAMPLE; ++s) sample[s] = v[s * stride];
        qsort(sample, SAMPLE, sizeof(double), compare_doubles);
        const Py_ssize_t at = k * SAMPLE / n;
        const double low = sample[at - MARGIN < 0 ? 0 : at - MARGIN];
        const double high = sample[at + MARGIN >= SAMPLE ? SAMPLE - 1 : at + MARGIN];
        Py_ssize_t below = 0, band = 0;
        for (Py_ssize_t i = 0; i < n; ++i) {
            below += v[i] < low;
            band += (v[i] >= low) & (v[i] <= high);
        }
        if (k - below_too >= below && k < below + band) { /* the band holds the ranks: only it, at the front */
            count = 0;
            for (Py_ssize_t i = 0; i < n; ++i) {
                const double x = v[i];
                v[count] = x;
                count += (x >= low) & (x <= high);
            }
            offset = below;
        }
    }
    const Py_ssize_t local = k - offset;
    *at_k = select_rank(v, count, local);
    if (below_too) {
        double best = v[0];
        for (Py_ssize_t i = 1; i < local; ++i)
            if (v[i] > best) best = v[i];
        *before_k = best;
    }
}

static PyObject *py_abs_median(PyObject *self, PyObject *args) {
    Py_buffer values;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*", &values)) return NULL;
    PyObject *result = NULL;
    const Py_ssize_t n = values.len / 8;
    if (values.len != n * 8) {
        PyErr_SetString(PyExc_ValueError, "abs_median: the values are not float64");
        goto done;
    }
    double *magnitude = n ? malloc((size_t)n * sizeof(double)) : NULL;
    int usable = n > 0 && magnitude != NULL;
    for (Py_ssize_t i = 0; usable && i < n; ++i) {
        magnitude[i] = fabs(((const double *)values.buf)[i]);
        if (isnan(magnitude[i])) usable = 0;
    }
    const Py_ssize_t k = n / 2;
    const int even = n % 2 == 0;
    double at_k = 0.0, before_k = 0.0;
    if (usable) ranked(magnitude, n, k, even, &at_k, &before_k);
    free(magnitude);
    if (usable && at_k != 0.0 && (!even || before_k != 0.0)) {
        result = PyFloat_FromDouble(even ? (before_k + at_k) / 2.0 : at_k);
    } else {
        result = Py_None;
        Py_INCREF(result);
    }
done:
    PyBuffer_Release(&values);
    return result;
}

/* The float64 values (n of them, set here) and the room for n - 1 int64 indices that restarts and elevation_steps take;
   0 with a ValueError naming the kernel when the buffers do not fit. */
static int steps_buffers(const Py_buffer *values, const Py_buffer *indices, const char *kernel, Py_ssize_t *n) {
    *n = values->len / 8;
    if (values->len != *n * 8 || indices->len < (*n > 0 ? *n - 1 : 0) * 8) {
        PyErr_Format(PyExc_ValueError, "%s: inconsistent buffer sizes", kernel);
        return 0;
    }
    return 1;
}

static PyObject *py_restarts(PyObject *self, PyObject *args) {
    Py_buffer turned, begins;
    double cut, half_spacing, restart;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*dddw*", &turned, &cut, &half_spacing, &restart, &begins)) return NULL;
    PyObject *result = NULL;
    Py_ssize_t n;
    if (!steps_buffers(&turned, &begins, "restarts", &n)) goto done;
    const double *t = turned.buf;
    int64_t *out = begins.buf, count = 0;
    /* In blocks, two passes each: the angles from the cut (vectorised), then where they fall back (rarely: the
       branch is predicted). laser_order._mod with its bounds given: the values changed in place, no +0.0. */
    enum { BLOCK = 2048 };
    double from_cut[BLOCK + 1];
    from_cut[BLOCK] = 0.0; /* (not compared: the first point has none before it) */
    for (Py_ssize_t start = 0; start < n; start += BLOCK) {
        const Py_ssize_t size = n - start < BLOCK ? n - start : BLOCK;
        const double *tb = t + start;
        from_cut[0] = from_cut[BLOCK]; /* the last angle of the block before */
        for (Py_ssize_t i = 0; i < size; ++i) {
            const double angle = (tb[i] - cut) + half_spacing;
            const double up = angle < 0.0 ? angle + 360.0 : angle;
            from_cut[i + 1] = angle >= 360.0 ? angle - 360.0 : up;
        }
        Py_ssize_t i = start == 0 ? 1 : 0;
#if defined(__SSE2__)
        /* Four differences at a time tell whether any falls back (the same subtractions and comparisons). */
        const __m128d limit = _mm_set1_pd(-restart);
        for (; i + 4 <= size; i += 4) {
            const __m128d early = _mm_sub_pd(_mm_loadu_pd(from_cut + i + 1), _mm_loadu_pd(from_cut + i));
            const __m128d late = _mm_sub_pd(_mm_loadu_pd(from_cut + i + 3), _mm_loadu_pd(from_cut + i + 2));
            if (_mm_movemask_pd(_mm_or_pd(_mm_cmplt_pd(early, limit), _mm_cmplt_pd(late, limit)))) {
                for (int j = 0; j < 4; ++j)
                    if (from_cut[i + j + 1] - from_cut[i + j] < -restart) out[count++] = start + i + j;
            }
        }
#endif
        for (; i < size; ++i) {
            if (from_cut[i + 1] - from_cut[i] < -restart) out[count++] = start + i;
        }
        from_cut[BLOCK] = from_cut[size];
    }
    result = PyLong_FromLongLong(count);
done:
    PyBuffer_Release(&turned);
    PyBuffer_Release(&begins);
    return result;
}

static PyObject *py_elevation_steps(PyObject *self, PyObject *args) {
    Py_buffer elevation, starts;
    double bound, decided;
    int falling;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*dpdw*", &elevation, &bound, &falling, &decided, &starts)) return NULL;
    PyObject *result = NULL;
    Py_ssize_t n;
    if (!steps_buffers(&elevation, &starts, "elevation_steps", &n)) goto done;
    const double *e = elevation.buf;
    int64_t *out = starts.buf, count = 0;
    for (Py_ssize_t i = 0; i + 1 < n; ++i) {
        const double rise = e[i + 1] - e[i];
        if (decided > 0.0 && !(fabs(rise - bound) > decided)) {
            count = -1;
            break;
        }
        if (falling ? rise < bound : rise > bound) out[count++] = i + 1;
    }
    result = PyLong_FromLongLong(count);
done:
    PyBuffer_Release(&elevation);
    PyBuffer_Release(&starts);
    return result;
}

static PyMethodDef methods[] = {
    {"ground_walk", py_ground_walk, METH_VARARGS, "GroundRemoval's walk up the columns (see the file)."},
    {"segment_labels", py_segment_labels, METH_VARARGS, "The breadth-first segmentation (see the file)."},
    {"vertical_pairs", py_vertical_pairs, METH_VARARGS, "The ground's vertical pairs (see the file)."},
    {"range_image", py_range_image, METH_VARARGS, "The range image's pixels of a scan's points (see the file)."},
    {"abs_median", py_abs_median, METH_VARARGS, "np.median of absolute values (see the file)."},
    {"restarts", py_restarts, METH_VARARGS, "Where the angle from the cut falls back (see the file)."},
    {"elevation_steps", py_elevation_steps, METH_VARARGS, "Where the elevation steps by a bound (see the file)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_projection_kernels", NULL, -1, methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__projection_kernels(void) { return PyModule_Create(&module); }
