"""Small rotation helpers (pure numpy, no ROS).

Conventions (REP-103):
  * quaternions are stored as (x, y, z, w), Hamilton product, and rotate
    body (FLU) vectors into the world frame (ENU): v_w = R(q) v_b;
  * Euler angles are roll, pitch, yaw about x, y, z with R = Rz(yaw) Ry(pitch) Rx(roll)
    (positive pitch = nose DOWN; ``road_grade = -pitch`` for a road-aligned body).
"""
from __future__ import annotations

import math

import numpy as np


def skew(v) -> np.ndarray:
    """S(v) such that S(v) @ u = v x u (paper 003, Eq. (31))."""
    return np.array([[0.0, -v[2], v[1]],
                     [v[2], 0.0, -v[0]],
                     [-v[1], v[0], 0.0]])


def quat_multiply(a, b) -> np.ndarray:
    """Hamilton product a * b, both (x, y, z, w)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ])


def quat_normalize(q) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    n = math.sqrt(float(q @ q))
    if not n > 0.0 or not math.isfinite(n):
        raise ValueError("cannot normalise a zero/non-finite quaternion")
    q = q / n
    return q if q[3] >= 0.0 else -q


def quat_to_rotmat(q) -> np.ndarray:
    """Rotation matrix of a (x, y, z, w) quaternion (paper 003, Eq. (26), with z = 1/|q|^2)."""
    x, y, z, w = q
    s = 2.0 / (x * x + y * y + z * z + w * w)
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    return np.array([[1.0 - yy - zz, xy - wz, xz + wy],
                     [xy + wz, 1.0 - xx - zz, yz - wx],
                     [xz - wy, yz + wx, 1.0 - xx - yy]])


def rotmat_to_quat(r) -> np.ndarray:
    """DCM -> (x, y, z, w); paper 003 Eq. (43), extended with the other three
    branches (Shepperd) so the case trace <= 0 noted below Eq. (43) is handled."""
    r = np.asarray(r, dtype=float)
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(1.0 + tr)          # s = 4 * w
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s]
    return quat_normalize(q)


def quat_from_rotvec(phi) -> np.ndarray:
    """Quaternion of the rotation vector phi (angle |phi| about phi/|phi|)."""
    px, py, pz = float(phi[0]), float(phi[1]), float(phi[2])
    ang = math.sqrt(px * px + py * py + pz * pz)
    if ang < 1e-12:
        return np.array([0.5 * px, 0.5 * py, 0.5 * pz, 1.0])
    k = math.sin(0.5 * ang) / ang
    return np.array([k * px, k * py, k * pz, math.cos(0.5 * ang)])


def quat_from_euler(roll, pitch, yaw) -> np.ndarray:
    """(x, y, z, w) of R = Rz(yaw) Ry(pitch) Rx(roll) (REP-103 fixed-axis rpy); vectorised:
    angle arrays of shape S give shape S + (4,)."""
    cr, sr = np.cos(0.5 * np.asarray(roll)), np.sin(0.5 * np.asarray(roll))
    cp, sp = np.cos(0.5 * np.asarray(pitch)), np.sin(0.5 * np.asarray(pitch))
    cy, sy = np.cos(0.5 * np.asarray(yaw)), np.sin(0.5 * np.asarray(yaw))
    return np.stack([
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    ], axis=-1)


def rotmat_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll), written out."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def euler_from_rotmat(r) -> tuple:
    """(roll, pitch, yaw) with R = Rz(yaw) Ry(pitch) Rx(roll)."""
    roll = math.atan2(r[2, 1], r[2, 2])
    pitch = -math.asin(max(-1.0, min(1.0, r[2, 0])))
    yaw = math.atan2(r[1, 0], r[0, 0])
    return roll, pitch, yaw


def euler_from_quat(q) -> tuple:
    return euler_from_rotmat(quat_to_rotmat(q))


def yaw_of_quat(x: float, y: float, z: float, w: float) -> float:
    """Yaw of R(q) = Rz(yaw) Ry(pitch) Rx(roll) for a quaternion of any norm, in scalar maths
    (one per message in the nodes); NaN for a zero or non-finite quaternion."""
    n = x * x + y * y + z * z + w * w
    yaw = math.atan2(2.0 * (w * z + x * y) / n, 1.0 - 2.0 * (y * y + z * z) / n) if n > 0.0 else math.nan
    return yaw if math.isfinite(yaw) else math.nan


def gravity_on_body_y(x: float, y: float, z: float, w: float) -> float:
    """R[2, 1] = sin(roll) cos(pitch) of the body -> world rotation q (any norm): the share of
    gravity a body-fixed accelerometer reads on its y axis; NaN for a quaternion far from unit."""
    n = x * x + y * y + z * z + w * w
    if not (math.isfinite(n) and n > 0.5):
        return math.nan
    return 2.0 * (y * z + w * x) / n


def gravity_on_body_y_variance(x: float, y: float, z: float, w: float, cov_xx: float, cov_xy: float,
                               cov_yy: float) -> float:
    """Variance of :func:`gravity_on_body_y` from the attitude error covariance about the fixed
    world x and y axes (the sensor_msgs/Imu and nav_msgs/Odometry convention): a small world
    rotation ``d theta`` moves the body's gravity by ``R^T (d theta x e_z)``, whose y entry is
    ``R[0, 1] d theta_y - R[1, 1] d theta_x`` (the rotation about the heading, i.e. the roll,
    at a small pitch). NaN for a quaternion far from unit or a covariance that is not finite."""
    n = x * x + y * y + z * z + w * w
    if not (math.isfinite(n) and n > 0.5):
        return math.nan
    r01 = 2.0 * (x * y - w * z) / n
    r11 = 1.0 - 2.0 * (x * x + z * z) / n
    variance = r11 * r11 * cov_xx - 2.0 * r11 * r01 * cov_xy + r01 * r01 * cov_yy
    return max(variance, 0.0) if math.isfinite(variance) else math.nan


def rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def wrap_angle(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi
