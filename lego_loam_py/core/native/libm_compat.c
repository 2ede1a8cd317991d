/*
 * Element-wise float32 functions that call the system C math library, for bit-exact parity with the
 * C++ LeGO-LOAM, whose column, ground and segmentation angles come from libm's atan2f. NumPy's own
 * float32/float64 atan2 round differently in the last bit, which moves points that lie exactly on a
 * range-image column boundary (about 4 % of the points of a real VLP-16 scan) to the neighbouring column.
 *
 *   atan2f(y, x, out): out[i] = atan2f(y[i], x[i]) for contiguous float32 buffers of equal length.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

static PyObject *py_atan2f(PyObject *self, PyObject *args) {
    Py_buffer y, x, out;
    if (!PyArg_ParseTuple(args, "y*y*w*", &y, &x, &out)) {
        return NULL;
    }
    PyObject *result = NULL;
    if (y.len != x.len || y.len != out.len || y.len % (Py_ssize_t)sizeof(float) != 0) {
        PyErr_SetString(PyExc_ValueError, "atan2f: buffers must be float32 arrays of equal length");
        goto done;
    }
    const float *yp = (const float *)y.buf, *xp = (const float *)x.buf;
    float *op = (float *)out.buf;
    Py_ssize_t n = y.len / (Py_ssize_t)sizeof(float);
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < n; ++i) {
        op[i] = atan2f(yp[i], xp[i]);
    }
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&y);
    PyBuffer_Release(&x);
    PyBuffer_Release(&out);
    return result;
}

static PyMethodDef methods[] = {
    {"atan2f", py_atan2f, METH_VARARGS, "atan2f(y, x, out): element-wise libm atan2f on float32 buffers."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_libm_compat", NULL, -1, methods};

PyMODINIT_FUNC PyInit__libm_compat(void) { return PyModule_Create(&module); }
