"""Compiled forms of the fusion ES-EKF's per-sample maths (see ``common.compiled``).

:func:`propagate` is ``FusionEKF._propagate`` (paper 003 Eqs. (22)-(29), (33)-(36)),
:func:`body_speed_rows` is ``_body_speed_rows`` (Eq. (46)), :func:`joseph_update` the gain and
Joseph-form covariance of ``_update`` (Eqs. (37)-(40), (44)), :func:`inject` is ``_inject``
(Eqs. (41)-(43)) and :func:`invariant_reset` is ``error_state.invariant_reset``. The numpy
methods are the definition and the test oracle (``test_model_kernels``): the same numbers to
1e-12.

One difference on purpose: the innovation covariance is inverted through its Cholesky factor,
so an ``S`` that is not positive definite is a numerical failure here, where the numpy path
inverts any non-singular ``S`` (an ``S = H P H^T + W`` that is not positive definite is one).
"""

from __future__ import annotations

import math

import numpy as np

from vehicle_estimation.estimators.common.compiled import kernel
from vehicle_estimation.estimators.common.small_linalg import cholesky_lower, cholesky_solve_rows, times_transpose

__all__ = ["UPDATE_APPLIED", "UPDATE_GATED", "UPDATE_FAILED", "body_speed_rows", "constraint_update", "imu_step",
           "inject", "invariant_reset", "joseph_update",
           "propagate", "warm_up"]

UPDATE_APPLIED, UPDATE_GATED, UPDATE_FAILED = 1, 0, -1
_IP, _IV, _IA, _IBA, _IBG, _IM, _IK = 0, 3, 6, 9, 12, 15, 17


@kernel
def _rotmat(x, y, z, w, R):
    """``rotations.quat_to_rotmat`` into ``R``."""
    s = 2.0 / (x * x + y * y + z * z + w * w)
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    R[0, 0], R[0, 1], R[0, 2] = 1.0 - yy - zz, xy - wz, xz + wy
    R[1, 0], R[1, 1], R[1, 2] = xy + wz, 1.0 - xx - zz, yz - wx
    R[2, 0], R[2, 1], R[2, 2] = xz - wy, yz + wx, 1.0 - xx - yy


@kernel
def propagate(dt, tau, f_prev, w_prev, ba, bg, g_vec, p, v, q, R, a_lp, w_lp, P, qd, q_out, R_out, P_out):
    """INS mechanisation and ``F P F^T + Q_d`` over ``dt``: ``p``, ``v``, ``a_lp``, ``w_lp`` in
    place; the new attitude in ``q_out``, ``R_out``; the covariance in ``P_out``."""
    s_b0, s_b1, s_b2 = f_prev[0] - ba[0], f_prev[1] - ba[1], f_prev[2] - ba[2]      # Eq. (22)
    w_b = np.empty(3)
    for i in range(3):
        w_b[i] = w_prev[i] - bg[i]
    s_n = np.empty(3)
    for i in range(3):
        s_n[i] = R[i, 0] * s_b0 + R[i, 1] * s_b1 + R[i, 2] * s_b2                     # Eq. (25)
    alpha = min(1.0, dt / tau)
    half = 0.5 * dt * dt
    for i in range(3):
        a = s_n[i] + g_vec[i]                                                          # Eq. (27)
        p[i] += dt * v[i] + half * a                                                    # Eq. (28)
        v[i] += dt * a                                                                  # Eq. (29)
        a_lp[i] += alpha * (a - a_lp[i])
        w_lp[i] += alpha * (w_b[i] - w_lp[i])
    # Eq. (23), body-rate right product.
    wx, wy, wz = w_b[0] * dt, w_b[1] * dt, w_b[2] * dt
    ang = math.sqrt(wx * wx + wy * wy + wz * wz)
    if ang > 1e-12:
        k = math.sin(0.5 * ang) / ang
        cw = math.cos(0.5 * ang)
    else:
        k, cw = 0.5, 1.0
    bx, by, bz = k * wx, k * wy, k * wz
    qx, qy, qz, qw = q[0], q[1], q[2], q[3]
    nx = qw * bx + qx * cw + qy * bz - qz * by
    ny = qw * by - qx * bz + qy * cw + qz * bx
    nz = qw * bz + qx * by - qy * bx + qz * cw
    nw = qw * cw - qx * bx - qy * by - qz * bz
    inv = 1.0 / math.sqrt(nx * nx + ny * ny + nz * nz + nw * nw)
    q_out[0], q_out[1], q_out[2], q_out[3] = nx * inv, ny * inv, nz * inv, nw * inv
    _rotmat(q_out[0], q_out[1], q_out[2], q_out[3], R_out)                            # Eq. (26)
    # Eq. (34), F = I + E with the old R; Eq. (35) as (F P) F^T.
    n = P.shape[0]
    F = np.zeros((n, n))
    for i in range(n):
        F[i, i] = 1.0
    F[0, 3] = F[1, 4] = F[2, 5] = dt
    F[3, 7], F[3, 8] = -dt * s_n[2], dt * s_n[1]
    F[4, 6], F[4, 8] = dt * s_n[2], -dt * s_n[0]
    F[5, 6], F[5, 7] = -dt * s_n[1], dt * s_n[0]
    for i in range(3):
        for j in range(3):
            F[3 + i, 9 + j] = -(dt * R[i, j])
            F[6 + i, 12 + j] = dt * R[i, j]
    FP = np.zeros((n, n))
    for i in range(n):
        for k in range(n):
            f = F[i, k]
            if f != 0.0:
                for j in range(n):
                    FP[i, j] += f * P[k, j]
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(n):
                f = F[j, k]
                if f != 0.0:
                    s += FP[i, k] * f
            P_out[i, j] = s
    for i in range(n):
        P_out[i, i] += qd[i]


@kernel
def body_speed_rows(R, Rm, v, rows, full_jacobian, mounting_pitch, mounting_yaw, pred, H):
    """Eq. (46): ``pred = (R_m R^T v)[rows]`` and its Jacobian ``H`` (attitude columns with
    ``full_jacobian``, the mounting pitch's and yaw's columns with ``mounting_pitch`` and
    ``mounting_yaw``)."""
    RmRt = np.empty((3, 3))
    vi = np.empty(3)
    for i in range(3):
        vi[i] = R[0, i] * v[0] + R[1, i] * v[1] + R[2, i] * v[2]
        for j in range(3):
            RmRt[i, j] = Rm[i, 0] * R[j, 0] + Rm[i, 1] * R[j, 1] + Rm[i, 2] * R[j, 2]
    H[:, :] = 0.0
    for k in range(rows.shape[0]):
        r = rows[k]
        pred[k] = Rm[r, 0] * vi[0] + Rm[r, 1] * vi[1] + Rm[r, 2] * vi[2]
        a0, a1, a2 = RmRt[r, 0], RmRt[r, 1], RmRt[r, 2]
        H[k, _IV], H[k, _IV + 1], H[k, _IV + 2] = a0, a1, a2
        if full_jacobian:   # -(row @ S(v))
            H[k, _IA] = -(a1 * v[2] - a2 * v[1])
            H[k, _IA + 1] = -(-a0 * v[2] + a2 * v[0])
            H[k, _IA + 2] = -(a0 * v[1] - a1 * v[0])
        if mounting_pitch or mounting_yaw:   # -S(R_m v_i)[r, 1:3], dm about base_link axes
            vb0 = Rm[0, 0] * vi[0] + Rm[0, 1] * vi[1] + Rm[0, 2] * vi[2]
            vb1 = Rm[1, 0] * vi[0] + Rm[1, 1] * vi[1] + Rm[1, 2] * vi[2]
            vb2 = Rm[2, 0] * vi[0] + Rm[2, 1] * vi[1] + Rm[2, 2] * vi[2]
            if r == 0:   # the row of -S(v_b): (v_b,z, -v_b,y), (0, v_b,x), (-v_b,x, 0)
                sp, sy = vb2, -vb1
            elif r == 1:
                sp, sy = 0.0, vb0
            else:
                sp, sy = -vb0, 0.0
            if mounting_pitch:
                H[k, _IM] = sp
            if mounting_yaw:
                H[k, _IM + 1] = sy


@kernel
def joseph_update(P, H, W, y, gate, use_gate, hold, P_out, dz):
    """Eqs. (37)-(40), (44): gain, error estimate ``dz`` and the Joseph-form covariance,
    symmetrised. ``hold``, orthonormal error-state directions as rows (or zeros: none), takes
    them out of the gain, K - hold^T hold K (Schmidt consider states: the yaw-rate bias, the
    speed's scale).
    Returns ``UPDATE_APPLIED``, ``UPDATE_GATED`` (``y^T S^-1 y`` above ``gate``) or
    ``UPDATE_FAILED`` (``S`` not positive definite, or ``dz`` not finite)."""
    n = P.shape[0]
    m = H.shape[0]
    PHt = np.empty((n, m))
    times_transpose(P, H, PHt)
    S = np.empty((m, m))
    for a in range(m):
        for b in range(m):
            s = W[a, b]
            for k in range(n):
                s += H[a, k] * PHt[k, b]
            S[a, b] = s
    L = np.empty((m, m))
    if not cholesky_lower(S, L):
        return UPDATE_FAILED
    if use_gate:
        Siy = np.empty((1, m))
        cholesky_solve_rows(L, y.reshape(1, m), Siy)
        d2 = 0.0
        for a in range(m):
            d2 += y[a] * Siy[0, a]
        if not d2 <= gate:
            return UPDATE_GATED
    K = np.empty((n, m))
    cholesky_solve_rows(L, PHt, K)                     # Eq. (37): K = P H^T S^-1
    for r in range(hold.shape[0]):
        for a in range(m):
            s = 0.0
            for i in range(n):
                s += hold[r, i] * K[i, a]
            if s != 0.0:
                for i in range(n):
                    K[i, a] -= hold[r, i] * s
    total = 0.0
    for i in range(n):
        s = 0.0
        for a in range(m):
            s += K[i, a] * y[a]
        dz[i] = s                                       # Eq. (40)
        total += s
    if not math.isfinite(total):
        return UPDATE_FAILED
    A = np.empty((n, n))                                # Eq. (44), Joseph: A P A^T + K W K^T
    for i in range(n):
        for j in range(n):
            s = 0.0
            for a in range(m):
                s += K[i, a] * H[a, j]
            A[i, j] = (1.0 if i == j else 0.0) - s
    AP = A @ P
    KW = K @ W
    for i in range(n):
        for j in range(i, n):
            s = 0.0
            for k in range(n):
                s += AP[i, k] * A[j, k]
            t = 0.0
            for a in range(m):
                t += KW[i, a] * K[j, a]
            P_out[i, j] = s + t
    for i in range(n):
        for j in range(i + 1, n):
            P_out[j, i] = P_out[i, j]
    return UPDATE_APPLIED


@kernel
def inject(dz, p, v, q, ba, bg, Rm, mounting, scale, q_out, R_out, Rm_out):
    """Eqs. (41)-(43): ``p``, ``v``, the biases and the speed's ``scale`` error (a 1-array) in
    place; the attitude ``q_new = q(-eps) (x) q`` into ``q_out``, ``R_out``; the mounting
    ``R(0, dm) R_m`` (dm about base_link axes) into ``Rm_out`` with ``mounting``."""
    for i in range(3):
        p[i] += dz[_IP + i]
        v[i] += dz[_IV + i]
    scale[0] += dz[_IK]
    ex, ey, ez = -dz[_IA], -dz[_IA + 1], -dz[_IA + 2]
    ang = math.sqrt(ex * ex + ey * ey + ez * ez)
    if ang > 1e-12:
        k = math.sin(0.5 * ang) / ang
        ax, ay, az, aw = k * ex, k * ey, k * ez, math.cos(0.5 * ang)
    else:
        ax, ay, az, aw = 0.5 * ex, 0.5 * ey, 0.5 * ez, 1.0
    bx, by, bz, bw = q[0], q[1], q[2], q[3]
    nx = aw * bx + ax * bw + ay * bz - az * by
    ny = aw * by - ax * bz + ay * bw + az * bx
    nz = aw * bz + ax * by - ay * bx + az * bw
    nw = aw * bw - ax * bx - ay * by - az * bz
    norm = math.sqrt(nx * nx + ny * ny + nz * nz + nw * nw)
    q_out[0], q_out[1], q_out[2], q_out[3] = nx / norm, ny / norm, nz / norm, nw / norm
    _rotmat(q_out[0], q_out[1], q_out[2], q_out[3], R_out)
    for i in range(3):
        ba[i] += dz[_IBA + i]
        bg[i] += dz[_IBG + i]
    if mounting:
        px, py, pz = 0.0, dz[_IM], dz[_IM + 1]
        ang = math.sqrt(px * px + py * py + pz * pz)
        if ang < 1e-12:
            mx, my, mz, mw = 0.5 * px, 0.5 * py, 0.5 * pz, 1.0
        else:
            k = math.sin(0.5 * ang) / ang
            mx, my, mz, mw = k * px, k * py, k * pz, math.cos(0.5 * ang)
        D = np.empty((3, 3))
        _rotmat(mx, my, mz, mw, D)
        for i in range(3):
            for j in range(3):
                Rm_out[i, j] = D[i, 0] * Rm[0, j] + D[i, 1] * Rm[1, j] + D[i, 2] * Rm[2, j]


@kernel
def invariant_reset(P, dz):
    """``P <- G P G^T`` in place, ``G = I + S(dv)`` at (v, eps) and ``S(dp)`` at (p, eps): the
    covariance follows the estimate's move ``dz`` (``error_state.invariant_reset``)."""
    n = P.shape[0]
    # G - I: nonzero in the rows of p and v (the error state's first six entries, _IP = 0 and
    # _IV = 3) and the attitude's columns.
    D = np.zeros((6, 3))
    for b, base in ((0, _IP), (3, _IV)):
        x, y, z = dz[base], dz[base + 1], dz[base + 2]
        D[b, 1], D[b, 2] = -z, y
        D[b + 1, 0], D[b + 1, 2] = z, -x
        D[b + 2, 0], D[b + 2, 1] = -y, x
    M = P.copy()                              # G P: rows p, v gain D P[eps, :]
    for r in range(6):
        for j in range(n):
            M[r, j] += D[r, 0] * P[_IA, j] + D[r, 1] * P[_IA + 1, j] + D[r, 2] * P[_IA + 2, j]
    for i in range(n):                        # (G P) G^T: columns p, v gain (G P)[:, eps] D^T
        for r in range(6):
            P[i, r] = M[i, r] + M[i, _IA] * D[r, 0] + M[i, _IA + 1] * D[r, 1] + M[i, _IA + 2] * D[r, 2]
        for j in range(6, n):
            P[i, j] = M[i, j]
    for i in range(n):
        for j in range(i + 1, n):
            s = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = s
            P[j, i] = s


@kernel
def constraint_update(R, Rm, v, rows, W, full_jacobian, pitch_min_speed, yaw_min_speed, mounting, hold, invariant,
                      p, ba, bg, scale, q, P, q_out, R_out, Rm_out, P_out):
    """The non-holonomic / standstill update (Eqs. (45)-(47), rows (3)) in one call: the body
    velocity ``rows`` should be zero, with noise ``W``: :func:`body_speed_rows` (with
    ``mounting``, the mounting pitch's column from a speed of ``pitch_min_speed`` up, the yaw's
    from ``yaw_min_speed``; infinite: none), then
    :func:`joseph_update` (no gate), :func:`inject` and, with ``invariant``,
    :func:`invariant_reset`. Returns the update's outcome; unless ``UPDATE_APPLIED``, nothing is
    written."""
    k, n = rows.shape[0], P.shape[0]
    pred, H, dz = np.empty(k), np.empty((k, n)), np.empty(n)
    speed_sq = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    body_speed_rows(R, Rm, v, rows, full_jacobian, mounting and speed_sq >= pitch_min_speed * pitch_min_speed,
                    mounting and speed_sq >= yaw_min_speed * yaw_min_speed, pred, H)
    outcome = joseph_update(P, H, W, -pred, 0.0, False, hold, P_out, dz)
    if outcome == UPDATE_APPLIED:
        inject(dz, p, v, q, ba, bg, Rm, mounting, scale, q_out, R_out, Rm_out)
        if invariant:
            invariant_reset(P_out, dz)
    return outcome


@kernel
def imu_step(dt, tau, f_prev, w_prev, ba, bg, g_vec, p, v, q, R, a_lp, w_lp, P, qd, rows, W, full_jacobian,
             pitch_min_speed, yaw_min_speed, mounting, hold, invariant, Rm, scale, q_out, R_out, Rm_out, P_out):
    """:func:`propagate`, then :func:`constraint_update` at the propagated state: one IMU sample
    of a moving vehicle. The outputs hold the propagation where the update is not applied
    (its outcome is returned)."""
    n = P.shape[0]
    q1, R1, P1 = np.empty(4), np.empty((3, 3)), np.empty((n, n))
    propagate(dt, tau, f_prev, w_prev, ba, bg, g_vec, p, v, q, R, a_lp, w_lp, P, qd, q1, R1, P1)
    outcome = constraint_update(R1, Rm, v, rows, W, full_jacobian, pitch_min_speed, yaw_min_speed, mounting,
                                hold, invariant, p, ba, bg, scale, q1, P1, q_out, R_out, Rm_out, P_out)
    if outcome != UPDATE_APPLIED:
        q_out[:] = q1
        R_out[:, :] = R1
        P_out[:, :] = P1
    return outcome


_warm = False


def warm_up(n: int = 18) -> None:
    """Compile (or load from the cache) every kernel of this module now, with the argument types
    the filter uses, so that the first sample of a drive does not wait for the compiler."""
    global _warm
    if _warm:
        return
    v3, P = np.zeros(3), np.eye(n)
    q, R = np.array([0.0, 0.0, 0.0, 1.0]), np.eye(3)
    propagate(0.01, 1.0, v3, v3, v3.copy(), v3.copy(), v3, v3.copy(), v3.copy(), q, R, v3.copy(), v3.copy(), P,
              np.zeros(n), np.empty(4), np.empty((3, 3)), np.empty((n, n)))
    H = np.zeros((2, n))
    body_speed_rows(R, R, v3, np.array([1, 2], dtype=np.int64), True, True, True, np.empty(2), H)
    dz = np.zeros(n)
    joseph_update(P, H, np.eye(2), np.zeros(2), 1.0, True, np.zeros((1, n)), np.empty((n, n)), dz)
    inject(dz, v3.copy(), v3.copy(), q, v3.copy(), v3.copy(), R, True, np.zeros(1), np.empty(4), np.empty((3, 3)),
           np.empty((3, 3)))
    invariant_reset(np.eye(n), dz)
    constraint_update(R, R, v3.copy(), np.array([1, 2], dtype=np.int64), np.eye(2), True, 1.0, 1.0, True,
                      np.zeros((1, n)), True, v3.copy(), v3.copy(), v3.copy(), np.zeros(1), q, P, np.empty(4),
                      np.empty((3, 3)), np.empty((3, 3)), np.empty((n, n)))
    imu_step(0.01, 1.0, v3, v3, v3.copy(), v3.copy(), v3, v3.copy(), v3.copy(), q, R, v3.copy(), v3.copy(), P,
             np.zeros(n), np.array([1, 2], dtype=np.int64), np.eye(2), True, 1.0, 1.0, True, np.zeros((1, n)), True, R,
             np.zeros(1), np.empty(4), np.empty((3, 3)), np.empty((3, 3)), np.empty((n, n)))
    _warm = True
