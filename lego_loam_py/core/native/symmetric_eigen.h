/*
 * Eigenvalues and eigenvectors of a symmetric 3x3 matrix by cyclic Jacobi rotations, shared by odometry_kernels.c
 * (the sweep-start odometry's degeneracy test) and geometry_kernels.c (the line fits of the scan-to-map
 * registration). Where NumPy goes through LAPACK (np.linalg.eigh), the values agree to rounding, not bit for bit.
 */
#ifndef LEGO_LOAM_SYMMETRIC_EIGEN_H
#define LEGO_LOAM_SYMMETRIC_EIGEN_H

#include <math.h>
#include <string.h>

/* Eigenvalues (ascending) and eigenvectors (columns of vectors, row-major) of a symmetric 3x3 matrix: cyclic
 * Jacobi rotations until the off-diagonal part vanishes against the diagonal. */
static inline void symmetric_eigen(const double *matrix, double *values, double *vectors) {
    double a[9], v[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
    memcpy(a, matrix, sizeof(a));
    for (int sweep = 0; sweep < 64; ++sweep) {
        const double off = a[1] * a[1] + a[2] * a[2] + a[5] * a[5];
        const double diagonal = a[0] * a[0] + a[4] * a[4] + a[8] * a[8];
        if (off == 0.0 || off <= 1e-36 * diagonal) {
            break;
        }
        for (int p = 0; p < 2; ++p) {
            for (int q = p + 1; q < 3; ++q) {
                const double apq = a[3 * p + q];
                if (apq == 0.0) {
                    continue;
                }
                const double tau = (a[3 * q + q] - a[3 * p + p]) / (2.0 * apq);
                const double t = (tau >= 0 ? 1.0 : -1.0) / (fabs(tau) + sqrt(1.0 + tau * tau));
                const double c = 1.0 / sqrt(1.0 + t * t), s = t * c;
                for (int k = 0; k < 3; ++k) { /* A <- A J (columns p, q) */
                    const double akp = a[3 * k + p], akq = a[3 * k + q];
                    a[3 * k + p] = c * akp - s * akq;
                    a[3 * k + q] = s * akp + c * akq;
                }
                for (int k = 0; k < 3; ++k) { /* A <- J^T A (rows p, q) */
                    const double apk = a[3 * p + k], aqk = a[3 * q + k];
                    a[3 * p + k] = c * apk - s * aqk;
                    a[3 * q + k] = s * apk + c * aqk;
                }
                a[3 * p + q] = a[3 * q + p] = 0.0;
                for (int k = 0; k < 3; ++k) {
                    const double vkp = v[3 * k + p], vkq = v[3 * k + q];
                    v[3 * k + p] = c * vkp - s * vkq;
                    v[3 * k + q] = s * vkp + c * vkq;
                }
            }
        }
    }
    int order[3] = {0, 1, 2};
    for (int i = 0; i < 3; ++i) {
        for (int j = i + 1; j < 3; ++j) {
            if (a[4 * order[j]] < a[4 * order[i]]) {
                const int swap = order[i];
                order[i] = order[j];
                order[j] = swap;
            }
        }
    }
    for (int i = 0; i < 3; ++i) {
        values[i] = a[4 * order[i]];
        for (int k = 0; k < 3; ++k) {
            vectors[3 * k + i] = v[3 * k + order[i]];
        }
    }
}

#endif
