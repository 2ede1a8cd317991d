/*
 * The Jacobian entries of the sweep-start frame (core/odometry/sweep.py, SweepStartFrame.rows), shared by
 * feature_kernels.c (sweep_rows) and odometry_kernels.c (sweep_block): coeff . d/dtheta_p [R(s theta)^T (p - s t)]
 * for the coefficient row (ax, ay, az) and parameter p (0-5: rx, ry, rz, tx, ty, tz), from the point's cosines and
 * sines of s theta, its time s and the frame's partial products q = p - s t, u = Rz q, v = Rx u.
 */
#ifndef LEGO_LOAM_SWEEP_JACOBIAN_H
#define LEGO_LOAM_SWEEP_JACOBIAN_H

static inline double sweep_jacobian_entry(int p, double ax, double ay, double az, double cx, double sx, double cy,
                                          double sy, double cz, double sz, double s, double qx, double qy, double qz,
                                          double ux, double uy, double vz) {
    /* coeff^T Ry, then coeff^T Ry Rx (see SweepStartFrame.rows). */
    const double bx = ax * cy + az * sy, by = ay, bz = -ax * sy + az * cy;
    const double cx_ = bx, cy_ = by * cx - bz * sx;
    double value, f1, f2;
    switch (p) {
        case 0:
            f1 = -sx * uy + cx * qz;
            f2 = -cx * uy - sx * qz;
            value = by * f1 + bz * f2;
            break;
        case 1:
            f1 = -sy * ux - cy * vz;
            f2 = cy * ux - sy * vz;
            value = ax * f1 + az * f2;
            break;
        case 2:
            f1 = -sz * qx + cz * qy;
            f2 = -cz * qx - sz * qy;
            value = cx_ * f1 + cy_ * f2;
            break;
        case 3:
            value = -(cx_ * cz - cy_ * sz);
            break;
        case 4:
            value = -(cx_ * sz + cy_ * cz);
            break;
        default:
            value = -(by * sx + bz * cx);
            break;
    }
    return value * s;
}

#endif
