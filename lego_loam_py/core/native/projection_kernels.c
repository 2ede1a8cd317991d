/*
 * imageProjection's loops that NumPy cannot express, in C. The module that calls them
 * (core/projection/segmentation.py) keeps its SciPy version as the fallback when this extension is not built, and
 * tests/test_segmentation.py compares the two.
 *
 * components(nodes, lower, upper, component) -> count
 *   The connected components of an undirected graph of `nodes` nodes whose edges join lower[k] and upper[k]
 *   (int64 arrays of equal length, every index in [0, nodes)): union-find with path halving, then each node's
 *   component numbered 0, 1, ... in the order of the components' lowest nodes. Writes component (nodes,) int64
 *   and returns the number of components. Runs without the GIL (the offline runner projects on a thread of its
 *   own beside featureAssociation).
 *
 * ground_walk(x, y, z, top, columns, ground, far, on_plane, slope, tolerance)
 *   GroundRemoval._refine_ground's walk up the columns (core/projection/ground.py), column by column instead of
 *   row by row, with its float64 operations in its order (built with -ffp-contract=off): x, y, z (top, columns)
 *   float32 coordinates, taken as float64 (exactly); ground, far and on_plane (top, columns) bool (ground rewritten
 *   in place). In each column, from the lowest row up, a ground candidate is kept when the column has no kept
 *   point yet and it is on the plane, or when |z - z_last| <= hypot(x - x_last, y - y_last) * slope + tolerance
 *   and it is on the plane or far; a kept point becomes the column's last. Runs without the GIL.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <math.h>
#include <stdlib.h>

static inline int64_t find_root(int64_t *parent, int64_t node) {
    while (parent[node] != node) {
        parent[node] = parent[parent[node]];
        node = parent[node];
    }
    return node;
}

static PyObject *py_components(PyObject *self, PyObject *args) {
    Py_ssize_t nodes;
    Py_buffer lower, upper, component;
    (void)self;
    if (!PyArg_ParseTuple(args, "ny*y*w*", &nodes, &lower, &upper, &component)) {
        return NULL;
    }
    PyObject *result = NULL;
    const Py_ssize_t edges = lower.len / 8;
    if (nodes < 0 || lower.len != edges * 8 || upper.len != lower.len || component.len != nodes * 8) {
        PyErr_SetString(PyExc_ValueError, "components: inconsistent buffer sizes");
        goto done;
    }
    const int64_t *a = lower.buf, *b = upper.buf;
    int64_t *parent = component.buf; /* the forest lives in the output until it is numbered */
    int bad = 0;
    int64_t count = 0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < nodes; ++i) parent[i] = i;
    for (Py_ssize_t k = 0; k < edges; ++k) {
        if (a[k] < 0 || a[k] >= nodes || b[k] < 0 || b[k] >= nodes) {
            bad = 1;
            break;
        }
        int64_t ra = find_root(parent, a[k]), rb = find_root(parent, b[k]);
        if (ra != rb) {
            if (ra < rb) parent[rb] = ra; /* the lower node is the root: a root is its component's lowest node */
            else parent[ra] = rb;
        }
    }
    if (!bad) {
        /* Every node's parent is at most the node (a root is its set's lowest node, and path halving only moves
           a node up to an ancestor): in node order, each parent is already numbered when its node comes. */
        for (Py_ssize_t i = 0; i < nodes; ++i) {
            const int64_t p = parent[i];
            parent[i] = p == i ? count++ : parent[p];
        }
    }
    Py_END_ALLOW_THREADS
    if (bad) {
        PyErr_SetString(PyExc_ValueError, "components: an edge names a node outside [0, nodes)");
        goto done;
    }
    result = PyLong_FromLongLong(count);
done:
    PyBuffer_Release(&lower);
    PyBuffer_Release(&upper);
    PyBuffer_Release(&component);
    return result;
}

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
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t c = 0; c < columns; ++c) {
        int seeded = 0;
        double last_x = 0.0, last_y = 0.0, last_z = 0.0;
        for (Py_ssize_t r = 0; r < top; ++r) {
            const Py_ssize_t i = r * columns + c;
            if (!keep[i]) continue;
            const double px = x[i], py = y[i], pz = z[i];
            int accepted;
            if (!seeded) {
                accepted = planar[i] != 0;
            } else {
                accepted = (is_far[i] || planar[i]) && rises_within(px - last_x, py - last_y, pz - last_z, slope,
                                                                     tolerance);
            }
            keep[i] = (uint8_t)accepted;
            if (accepted) {
                last_x = px;
                last_y = py;
                last_z = pz;
                seeded = 1;
            }
        }
    }
    Py_END_ALLOW_THREADS
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

static PyMethodDef methods[] = {
    {"components", py_components, METH_VARARGS, "Connected components of an undirected graph (see the file)."},
    {"ground_walk", py_ground_walk, METH_VARARGS, "GroundRemoval's walk up the columns (see the file)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_projection_kernels", NULL, -1, methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__projection_kernels(void) { return PyModule_Create(&module); }
