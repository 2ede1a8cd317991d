/*
 * The sweep-start odometry's Gauss-Newton iterations (core/odometry/laser_odometry.py, SweepStartOdometry), one
 * block at a time, in C. A block's correspondences and weights are fixed, so its iterations need nothing from
 * Python: each evaluates the residuals and their Jacobian at the estimate, solves the 3x3 normal equations
 * (projected onto the well-constrained directions found on the stage's first iteration), shortens the step until
 * the block's cost does not increase, and stops once a step falls below the convergence thresholds. In NumPy a
 * block's iterations cost some hundred small calls each (a stage holds a few hundred points): far more than their
 * arithmetic.
 *
 * Unlike the other kernels this one is not bit-for-bit the NumPy loop it replaces: its sums run point by point
 * and its 3x3 solve and eigen decomposition are its own (partial pivoting; cyclic Jacobi), where NumPy goes
 * through BLAS and LAPACK. The per-point arithmetic (sweep-start points in float32, plane distances in the
 * planes' precision, line offsets, Jacobian rows) is that of sweep.py and laser_odometry.py, operation by operation
 * (built with -ffp-contract=off). tests/test_odometry_kernels.py holds the two within a tolerance, on blocks
 * recorded from simulated drives.
 *
 * sweep_block(theta, active, terms, prior_weight, iterations, first, threshold, projection, degenerate,
 *             convergence_rotation, convergence_translation, halvings) -> (iterations done, smallest eigenvalue)
 *   theta (6,) float64, updated in place: (rx, ry, rz, tx, ty, tz) of the sweep. active (3,) int64: the
 *   stage's parameters (a rotation when < 3). terms: a list of (kind, xyz, s, weight, first, second, coeff)
 *   with kind 0 (planes in float32: first the (n, 3) float32 normals, second the (n,) float32 offsets), 1 (the
 *   same in float64) or 2 (lines: first the (n, 3) float64 anchors, second the (n, 3) float64 unit
 *   directions); xyz (3, n), s (n,), weight (n,) float64; coeff (n, 3) float64 for planes, (n, 3, 3) for lines.
 *   prior_weight > 0 adds sqrt(prior_weight) * theta_k for each active rotation. first != 0: the first
 *   iteration finds the degenerate directions (eigenvalues of the normal matrix below threshold, counted from
 *   the smallest up to the first that is not) and writes projection (9,) float64 and degenerate (1,) uint8;
 *   otherwise those are read. Returns the iterations run (at most ``iterations``) and the smallest eigenvalue
 *   (NaN when first is 0).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <math.h>
#include <string.h>

#include "sweep_jacobian.h"
#include "symmetric_eigen.h"

#define MAX_TERMS 4
#define TRIG_SLOTS 2

typedef struct {
    int kind; /* 0 planes float32, 1 planes float64, 2 lines */
    Py_ssize_t n;
    const double *x, *y, *z, *s, *weight, *coeff;
    const float *normal32, *offset32;
    const double *normal64, *offset64, *anchor, *along;
    /* cos and sin of theta_k * s for the last angles seen (TRIG_SLOTS per angle), by the angle's bits */
    double *trig;      /* [3][TRIG_SLOTS][2][n] */
    uint64_t bits[3][TRIG_SLOTS];
    int valid[3][TRIG_SLOTS];
    int next[3];
    Py_buffer buffers[6];
    int held;
} Term;

/* A float64 rounded to float32 (the sweep-start points are float32). Through a volatile: GCC 12's SLP vectoriser
 * at -O2 was seen to drop this rounding on one branch of evaluate() (the points then kept float64 precision). */
static inline float to_float32(double value) {
    volatile float rounded = (float)value;
    return rounded;
}

static uint64_t bits_of(double value) {
    uint64_t bits;
    memcpy(&bits, &value, sizeof(bits));
    return bits;
}

/* The (cos, sin) arrays of angle * s for parameter k of the term, from its slots or computed into one. */
static const double *term_trig(Term *t, int k, double angle) {
    const uint64_t bits = bits_of(angle);
    for (int slot = 0; slot < TRIG_SLOTS; ++slot) {
        if (t->valid[k][slot] && t->bits[k][slot] == bits) {
            return t->trig + ((Py_ssize_t)(k * TRIG_SLOTS + slot) * 2) * t->n;
        }
    }
    const int slot = t->next[k];
    t->next[k] = (slot + 1) % TRIG_SLOTS;
    double *out = t->trig + ((Py_ssize_t)(k * TRIG_SLOTS + slot) * 2) * t->n;
    for (Py_ssize_t i = 0; i < t->n; ++i) {
        const double a = angle * t->s[i];
        out[i] = cos(a);
        out[t->n + i] = sin(a);
    }
    t->bits[k][slot] = bits;
    t->valid[k][slot] = 1;
    return out;
}

/* The block's cost (sum of squared weighted residuals, the prior's included) at theta; with ata and atb, also the
 * normal equations of its Jacobian over the active parameters (ata row-major 3x3, atb = J^T (-r)). */
static double evaluate(Term *terms, int n_terms, const double *theta, const int64_t *active, double prior_weight,
                       double *ata, double *atb) {
    double cost = 0.0;
    if (ata != NULL) {
        memset(ata, 0, 9 * sizeof(double));
        memset(atb, 0, 3 * sizeof(double));
    }
    for (int term = 0; term < n_terms; ++term) {
        Term *t = &terms[term];
        const Py_ssize_t n = t->n;
        const double *trig_x = term_trig(t, 0, theta[0]), *trig_y = term_trig(t, 1, theta[1]);
        const double *trig_z = term_trig(t, 2, theta[2]);
        for (Py_ssize_t i = 0; i < n; ++i) {
            const double cx = trig_x[i], sx = trig_x[n + i], cy = trig_y[i], sy = trig_y[n + i];
            const double cz = trig_z[i], sz = trig_z[n + i], s = t->s[i];
            const double qx = t->x[i] - theta[3] * s, qy = t->y[i] - theta[4] * s, qz = t->z[i] - theta[5] * s;
            const double ux = cz * qx + sz * qy, uy = -sz * qx + cz * qy;
            const double vy = cx * uy + sx * qz, vz = -sx * uy + cx * qz;
            const float p0 = to_float32(cy * ux - sy * vz), p1 = to_float32(vy), p2 = to_float32(sy * ux + cy * vz);
            double r[3];
            int m;
            if (t->kind == 0) {
                const float *nv = t->normal32 + 3 * i;
                const float d = nv[0] * p0 + nv[1] * p1 + nv[2] * p2 + t->offset32[i];
                r[0] = t->weight[i] * (double)d;
                m = 1;
            } else if (t->kind == 1) {
                const double *nv = t->normal64 + 3 * i;
                const double d = nv[0] * (double)p0 + nv[1] * (double)p1 + nv[2] * (double)p2 + t->offset64[i];
                r[0] = t->weight[i] * d;
                m = 1;
            } else {
                const double *a = t->anchor + 3 * i, *u = t->along + 3 * i;
                const double d0 = (double)p0 - a[0], d1 = (double)p1 - a[1], d2 = (double)p2 - a[2];
                const double dot = d0 * u[0] + d1 * u[1] + d2 * u[2];
                r[0] = t->weight[i] * (d0 - dot * u[0]);
                r[1] = t->weight[i] * (d1 - dot * u[1]);
                r[2] = t->weight[i] * (d2 - dot * u[2]);
                m = 3;
            }
            for (int c = 0; c < m; ++c) {
                cost += r[c] * r[c];
                if (ata == NULL) {
                    continue;
                }
                const double *row = t->coeff + 3 * (i * m + c);
                double j[3];
                for (int k = 0; k < 3; ++k) {
                    j[k] = sweep_jacobian_entry((int)active[k], row[0], row[1], row[2], cx, sx, cy, sy, cz, sz, s, qx, qy,
                                          qz, ux, uy, vz);
                }
                for (int a = 0; a < 3; ++a) {
                    for (int b = 0; b < 3; ++b) {
                        ata[3 * a + b] += j[a] * j[b];
                    }
                    atb[a] += j[a] * -r[c];
                }
            }
        }
    }
    if (prior_weight > 0) {
        const double root = sqrt(prior_weight);
        for (int k = 0; k < 3; ++k) {
            if (active[k] < 3) {
                const double r = root * theta[active[k]];
                cost += r * r;
                if (ata != NULL) {
                    ata[4 * k] += root * root;
                    atb[k] += root * -r;
                }
            }
        }
    }
    return cost;
}

/* x solving ata x = atb: Gaussian elimination with partial pivoting; a singular matrix gets the minimum-norm
 * least-squares solution (eigenvalues within 3 eps of the largest count as zero, as lstsq's default). */
static void solve3(const double *ata, const double *atb, double *x) {
    double m[3][4];
    for (int i = 0; i < 3; ++i) {
        m[i][0] = ata[3 * i];
        m[i][1] = ata[3 * i + 1];
        m[i][2] = ata[3 * i + 2];
        m[i][3] = atb[i];
    }
    int singular = 0;
    for (int col = 0; col < 3 && !singular; ++col) {
        int pivot = col;
        for (int row = col + 1; row < 3; ++row) {
            if (fabs(m[row][col]) > fabs(m[pivot][col])) {
                pivot = row;
            }
        }
        if (m[pivot][col] == 0.0) {
            singular = 1;
            break;
        }
        if (pivot != col) {
            for (int k = 0; k < 4; ++k) {
                const double swap = m[col][k];
                m[col][k] = m[pivot][k];
                m[pivot][k] = swap;
            }
        }
        for (int row = col + 1; row < 3; ++row) {
            const double factor = m[row][col] / m[col][col];
            for (int k = col; k < 4; ++k) {
                m[row][k] -= factor * m[col][k];
            }
        }
    }
    if (!singular) {
        for (int row = 2; row >= 0; --row) {
            double value = m[row][3];
            for (int k = row + 1; k < 3; ++k) {
                value -= m[row][k] * x[k];
            }
            x[row] = value / m[row][row];
        }
        return;
    }
    double values[3], vectors[9];
    symmetric_eigen(ata, values, vectors);
    const double largest = fmax(fabs(values[0]), fabs(values[2]));
    const double cutoff = 3.0 * 2.220446049250313e-16 * largest;
    x[0] = x[1] = x[2] = 0.0;
    for (int i = 0; i < 3; ++i) {
        if (fabs(values[i]) <= cutoff) {
            continue;
        }
        const double along = (vectors[i] * atb[0] + vectors[3 + i] * atb[1] + vectors[6 + i] * atb[2]) / values[i];
        for (int k = 0; k < 3; ++k) {
            x[k] += along * vectors[3 * k + i];
        }
    }
}

static int all_finite(const double *values, int n) {
    for (int i = 0; i < n; ++i) {
        if (!isfinite(values[i])) {
            return 0;
        }
    }
    return 1;
}

static void release_terms(Term *terms, int n_terms) {
    for (int i = 0; i < n_terms; ++i) {
        for (int b = 0; b < terms[i].held; ++b) {
            PyBuffer_Release(&terms[i].buffers[b]);
        }
        PyMem_Free(terms[i].trig);
    }
}

/* Parse one term tuple into t (its buffers held); 0 on success, -1 with an exception set. */
static int parse_term(PyObject *item, Term *t) {
    memset(t, 0, sizeof(*t));
    int kind;
    if (!PyArg_ParseTuple(item, "iy*y*y*y*y*y*", &kind, &t->buffers[0], &t->buffers[1], &t->buffers[2],
                          &t->buffers[3], &t->buffers[4], &t->buffers[5])) {
        return -1;
    }
    t->held = 6;
    t->kind = kind;
    const Py_ssize_t n = t->buffers[1].len / (Py_ssize_t)sizeof(double);
    const Py_ssize_t d = (Py_ssize_t)sizeof(double), f = (Py_ssize_t)sizeof(float);
    const int m = kind == 2 ? 3 : 1;
    int ok = kind >= 0 && kind <= 2 && t->buffers[0].len == 3 * n * d && t->buffers[1].len == n * d &&
             t->buffers[2].len == n * d && t->buffers[5].len == n * m * 3 * d;
    if (kind == 0) {
        ok = ok && t->buffers[3].len == 3 * n * f && t->buffers[4].len == n * f;
    } else if (kind == 1) {
        ok = ok && t->buffers[3].len == 3 * n * d && t->buffers[4].len == n * d;
    } else {
        ok = ok && t->buffers[3].len == 3 * n * d && t->buffers[4].len == 3 * n * d;
    }
    if (!ok) {
        PyErr_SetString(PyExc_ValueError, "sweep_block: inconsistent term buffer sizes");
        return -1;
    }
    t->n = n;
    t->x = t->buffers[0].buf;
    t->y = t->x + n;
    t->z = t->y + n;
    t->s = t->buffers[1].buf;
    t->weight = t->buffers[2].buf;
    t->coeff = t->buffers[5].buf;
    if (kind == 0) {
        t->normal32 = t->buffers[3].buf;
        t->offset32 = t->buffers[4].buf;
    } else if (kind == 1) {
        t->normal64 = t->buffers[3].buf;
        t->offset64 = t->buffers[4].buf;
    } else {
        t->anchor = t->buffers[3].buf;
        t->along = t->buffers[4].buf;
    }
    t->trig = PyMem_Malloc(sizeof(double) * (size_t)(3 * TRIG_SLOTS * 2 * (n > 0 ? n : 1)));
    if (t->trig == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    return 0;
}

static PyObject *py_sweep_block(PyObject *self, PyObject *args) {
    Py_buffer theta_buffer, active_buffer, projection_buffer, degenerate_buffer;
    PyObject *term_list;
    double prior_weight, threshold, convergence_rotation, convergence_translation;
    int iterations, first, halvings;
    (void)self;
    if (!PyArg_ParseTuple(args, "w*y*O!diidw*w*ddi", &theta_buffer, &active_buffer, &PyList_Type, &term_list,
                          &prior_weight, &iterations, &first, &threshold, &projection_buffer, &degenerate_buffer,
                          &convergence_rotation, &convergence_translation, &halvings)) {
        return NULL;
    }
    PyObject *result = NULL;
    Term terms[MAX_TERMS];
    int n_terms = 0;
    const Py_ssize_t listed = PyList_GET_SIZE(term_list);
    if (theta_buffer.len != 6 * (Py_ssize_t)sizeof(double) || active_buffer.len != 3 * 8 ||
        projection_buffer.len != 9 * (Py_ssize_t)sizeof(double) || degenerate_buffer.len != 1 || listed < 1 ||
        listed > MAX_TERMS) {
        PyErr_SetString(PyExc_ValueError, "sweep_block: inconsistent buffer sizes or number of terms");
        goto done;
    }
    const int64_t *active = active_buffer.buf;
    for (int k = 0; k < 3; ++k) {
        if (active[k] < 0 || active[k] > 5) {
            PyErr_SetString(PyExc_ValueError, "sweep_block: parameters are 0 to 5");
            goto done;
        }
    }
    for (Py_ssize_t i = 0; i < listed; ++i) {
        if (parse_term(PyList_GET_ITEM(term_list, i), &terms[n_terms]) < 0) {
            release_terms(terms, n_terms + 1);
            n_terms = 0;
            goto done;
        }
        ++n_terms;
    }
    double *theta = theta_buffer.buf, *projection = projection_buffer.buf;
    uint8_t *degenerate = degenerate_buffer.buf;
    const double to_degrees = 180.0 / 3.141592653589793;
    double smallest = NAN;
    int done_iterations = 0;
    for (int iteration = 0; iteration < iterations; ++iteration) {
        ++done_iterations;
        double ata[9], atb[3], x[3];
        const double reference = evaluate(terms, n_terms, theta, active, prior_weight, ata, atb);
        solve3(ata, atb, x);
        if (first) {
            double values[3], vectors[9];
            symmetric_eigen(ata, values, vectors);
            smallest = values[0];
            int keep[3] = {1, 1, 1};
            *degenerate = 0;
            for (int i = 0; i < 3; ++i) { /* from the smallest up to the first >= threshold */
                if (values[i] < threshold) {
                    keep[i] = 0;
                    *degenerate = 1;
                } else {
                    break;
                }
            }
            for (int r = 0; r < 3; ++r) {
                for (int c = 0; c < 3; ++c) {
                    double sum = 0.0;
                    for (int i = 0; i < 3; ++i) {
                        sum += keep[i] ? vectors[3 * r + i] * vectors[3 * c + i] : 0.0;
                    }
                    projection[3 * r + c] = sum;
                }
            }
            first = 0;
        }
        if (*degenerate) {
            double projected[3];
            for (int r = 0; r < 3; ++r) {
                projected[r] = projection[3 * r] * x[0] + projection[3 * r + 1] * x[1] + projection[3 * r + 2] * x[2];
            }
            memcpy(x, projected, sizeof(x));
        }
        /* The largest of x, x/2, ... that does not increase the block's cost (none: no step). */
        double step[3] = {x[0], x[1], x[2]}, taken[3] = {0.0, 0.0, 0.0};
        for (int h = 0; h <= halvings; ++h) {
            double trial[6];
            memcpy(trial, theta, sizeof(trial));
            for (int k = 0; k < 3; ++k) {
                trial[active[k]] += step[k];
            }
            if (all_finite(trial, 6)) {
                const double cost = evaluate(terms, n_terms, trial, active, prior_weight, NULL, NULL);
                if (isfinite(cost) && cost <= reference) {
                    memcpy(taken, step, sizeof(taken));
                    break;
                }
            }
            for (int k = 0; k < 3; ++k) {
                step[k] = step[k] / 2;
            }
        }
        double rotation = 0.0, translation = 0.0;
        for (int k = 0; k < 3; ++k) {
            theta[active[k]] += taken[k];
            if (active[k] < 3) {
                const double degrees = taken[k] * to_degrees;
                rotation += degrees * degrees;
            } else {
                const double centimetres = taken[k] * 100.0;
                translation += centimetres * centimetres;
            }
        }
        for (int k = 0; k < 6; ++k) {
            if (!isfinite(theta[k])) {
                theta[k] = 0.0;
            }
        }
        if (sqrt(rotation) < convergence_rotation && sqrt(translation) < convergence_translation) {
            break;
        }
    }
    result = Py_BuildValue("(id)", done_iterations, smallest);
done:
    release_terms(terms, n_terms);
    PyBuffer_Release(&theta_buffer);
    PyBuffer_Release(&active_buffer);
    PyBuffer_Release(&projection_buffer);
    PyBuffer_Release(&degenerate_buffer);
    return result;
}

static PyMethodDef methods[] = {
    {"sweep_block", py_sweep_block, METH_VARARGS, "One block of the sweep-start odometry's iterations (see the file)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_odometry_kernels", NULL, -1, methods, NULL, NULL, NULL,
                                    NULL};

PyMODINIT_FUNC PyInit__odometry_kernels(void) { return PyModule_Create(&module); }
