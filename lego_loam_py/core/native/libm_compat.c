/*
 * Element-wise float32 functions that call the system C math library, for bit-exact parity with the
 * C++ LeGO-LOAM, whose column, ground and segmentation angles come from libm's atan2f. NumPy's own
 * float32/float64 atan2 round differently in the last bit, which moves points that lie exactly on a
 * range-image column boundary (about 4 % of the points of a real VLP-16 scan) to the neighbouring column.
 *
 *   atan2f(y, x, out): out[i] = atan2f(y[i], x[i]) for contiguous float32 buffers of equal length.
 *
 *   atan2f_steps(y, x, guess, low_cos, low_sin, high_cos, high_sin, scale, step, confirmed): the passes of
 *   parity.atan2f_decisions.Atan2fSteps.count in one, each float32 operation the one NumPy does there, in its
 *   order (built with -ffp-contract=off): the guessed step of each element from its pseudo-angle's bin in guess
 *   (int64), confirmed where the two cross products with the step's edge directions (float32 tables indexed by
 *   step) clear their rounding bound. y, x float32; step int64 and confirmed uint8 (bool), all of one length.
 *
 *   azimuth_fraction(points, columns, start, turn, diff, out): sweep.relative_time_from_azimuth in one pass, with
 *   NumPy's operations and types: for each row of points (n x columns float32, x and y first), the float64
 *   orientation -atan2f(y, x), minus start, modulo turn as np.mod takes it (fmod, moved into the sign of turn, a
 *   zero given turn's sign), divided by diff and rounded to float32 into out (n float32).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>

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


static PyObject *py_atan2f_steps(PyObject *self, PyObject *args) {
    Py_buffer y, x, guess, low_cos, low_sin, high_cos, high_sin, step, confirmed;
    float scale;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*y*fw*w*", &y, &x, &guess, &low_cos, &low_sin, &high_cos, &high_sin,
                          &scale, &step, &confirmed)) {
        return NULL;
    }
    PyObject *result = NULL;
    const Py_ssize_t n = y.len / (Py_ssize_t)sizeof(float), bins = guess.len / 8;
    const Py_ssize_t steps = low_cos.len / (Py_ssize_t)sizeof(float);
    if (y.len != n * (Py_ssize_t)sizeof(float) || x.len != y.len || step.len != n * 8 || confirmed.len != n ||
        bins < 1 || guess.len != bins * 8 || low_cos.len != steps * (Py_ssize_t)sizeof(float) ||
        low_sin.len != low_cos.len || high_cos.len != low_cos.len || high_sin.len != low_cos.len) {
        PyErr_SetString(PyExc_ValueError, "atan2f_steps: inconsistent buffer sizes");
        goto done;
    }
    const int64_t *table = guess.buf;
    for (Py_ssize_t b = 0; b < bins; ++b) {
        if (table[b] < 0 || table[b] >= steps) {
            PyErr_SetString(PyExc_ValueError, "atan2f_steps: a guess outside the steps' tables");
            goto done;
        }
    }
    const float *yp = y.buf, *xp = x.buf, *lc = low_cos.buf, *ls = low_sin.buf, *hc = high_cos.buf,
                *hs = high_sin.buf;
    int64_t *out = step.buf;
    uint8_t *sure = confirmed.buf;
    const float last = (float)(bins - 1), unit = 0x1p-21f, tiny = 0x1p-120f;
    Py_BEGIN_ALLOW_THREADS
    /* In blocks, two passes each: the bins (vectorised: no load depends on an earlier one; through int32, which SSE2
       converts four floats at a time to, not int64), then the guesses and their checks. */
    enum { BLOCK = 2048 };
    int32_t bin[BLOCK];
    for (Py_ssize_t start = 0; start < n; start += BLOCK) {
        const Py_ssize_t size = n - start < BLOCK ? n - start : BLOCK;
        const float *yb = yp + start, *xb = xp + start;
        for (Py_ssize_t i = 0; i < size; ++i) {
            float position = yb[i] / (fabsf(xb[i]) + fabsf(yb[i])); /* in [-1, 1]; NaN at the origin */
            position = position + 1.0f;
            position = copysignf(position, xb[i]);
            position = position + 2.0f;
            position = position * scale;
            position = position <= last ? position : last; /* np.fmin: the top end, and NaN, into the last bin */
            bin[i] = (int32_t)position;
        }
        for (Py_ssize_t i = 0; i < size; ++i) {
            const float yi = yb[i], xi = xb[i];
            const int64_t k = table[bin[i]];
            const float bound = (fabsf(xi) + fabsf(yi)) * unit + tiny;
            const float below = yi * lc[k] - xi * ls[k], above = yi * hc[k] - xi * hs[k];
            out[start + i] = k;
            sure[start + i] = (uint8_t)((below > bound) & (above < -bound));
        }
    }
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&y);
    PyBuffer_Release(&x);
    PyBuffer_Release(&guess);
    PyBuffer_Release(&low_cos);
    PyBuffer_Release(&low_sin);
    PyBuffer_Release(&high_cos);
    PyBuffer_Release(&high_sin);
    PyBuffer_Release(&step);
    PyBuffer_Release(&confirmed);
    return result;
}

static PyObject *py_azimuth_fraction(PyObject *self, PyObject *args) {
    Py_buffer points, out;
    Py_ssize_t columns;
    double start, turn, diff;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*ndddw*", &points, &columns, &start, &turn, &diff, &out)) {
        return NULL;
    }
    PyObject *result = NULL;
    const Py_ssize_t n = out.len / (Py_ssize_t)sizeof(float);
    if (columns < 2 || out.len != n * (Py_ssize_t)sizeof(float) ||
        points.len != n * columns * (Py_ssize_t)sizeof(float)) {
        PyErr_SetString(PyExc_ValueError, "azimuth_fraction: inconsistent buffer sizes");
        goto done;
    }
    const float *p = points.buf;
    float *o = out.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < n; ++i) {
        const double orientation = -(double)atan2f(p[i * columns + 1], p[i * columns]);
        const double angle = orientation - start;
        double mod = fmod(angle, turn);
        if (turn != 0.0) { /* (NumPy's remainder: a zero divisor leaves fmod's NaN) */
            if (mod != 0.0) {
                if ((turn < 0.0) != (mod < 0.0)) {
                    mod += turn;
                }
            } else {
                mod = copysign(0.0, turn);
            }
        }
        o[i] = (float)(mod / diff);
    }
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&points);
    PyBuffer_Release(&out);
    return result;
}

static PyMethodDef methods[] = {
    {"atan2f", py_atan2f, METH_VARARGS, "atan2f(y, x, out): element-wise libm atan2f on float32 buffers."},
    {"atan2f_steps", py_atan2f_steps, METH_VARARGS, "Atan2fSteps.count's passes in one (see the file)."},
    {"azimuth_fraction", py_azimuth_fraction, METH_VARARGS, "relative_time_from_azimuth in one pass (see the file)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_libm_compat", NULL, -1, methods};

PyMODINIT_FUNC PyInit__libm_compat(void) { return PyModule_Create(&module); }
