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
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
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

static PyMethodDef methods[] = {
    {"components", py_components, METH_VARARGS, "Connected components of an undirected graph (see the file)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_projection_kernels", NULL, -1, methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__projection_kernels(void) { return PyModule_Create(&module); }
