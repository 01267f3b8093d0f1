"""Rigid transforms of the camera frames: (4, 4) float64 matrices, metres, angles in degrees
unless said."""

from __future__ import annotations

import math

import numba
import numpy as np


def rigid(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    """(4, 4) the rigid transform of rotation ``R`` (3, 3) (none by default) and translation
    ``t`` (3,) m (none by default)."""
    out = np.eye(4)
    out[:3, :3] = np.eye(3) if R is None else R
    out[:3, 3] = 0.0 if t is None else t
    return out


def invert(T: np.ndarray) -> np.ndarray:
    """(4, 4) inverse of a rigid transform."""
    R = T[:3, :3]
    return rigid(R.T, -R.T @ T[:3, 3])


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(M, 3) float32 ``points`` mapped by the (4, 4) rigid transform ``T``."""
    p = np.asarray(points, dtype=np.float64)
    return (p @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of the rotation matrix ``R`` (3, 3), degrees."""
    c = (float(np.trace(R)) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """(3,) the axis of the rotation matrix ``R`` (3, 3) times its angle, radians (the
    inverse of :func:`exp_so3`; at 180 degrees either of the two axes)."""
    angle = math.radians(rotation_angle_deg(R))
    if angle < 1e-12:
        return np.zeros(3)
    if math.sin(angle) < 1e-6:  # about 180 degrees: (R + I) / 2 = axis axis^T
        S = (np.asarray(R, dtype=np.float64) + np.eye(3)) / 2.0
        k = int(np.argmax(np.diag(S)))
        return S[:, k] / math.sqrt(S[k, k]) * angle
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return axis * (angle / (2.0 * math.sin(angle)))


def rotation_to_rpy_deg(R: np.ndarray) -> np.ndarray:
    """(3,) roll, pitch, yaw in degrees of ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (angles about
    the frame's x, y and z axes, the REP 103 convention)."""
    pitch = math.asin(max(-1.0, min(1.0, -float(R[2, 0]))))
    roll = math.atan2(float(R[2, 1]), float(R[2, 2]))
    yaw = math.atan2(float(R[1, 0]), float(R[0, 0]))
    return np.degrees([roll, pitch, yaw])


def rpy_deg_to_rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """(3, 3) ``Rz(yaw) Ry(pitch) Rx(roll)``, angles in degrees."""
    r, p, y = (math.radians(a) for a in (roll, pitch, yaw))
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), \
        math.cos(y), math.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


@numba.njit(cache=True, nogil=True)
def exp_so3(w):
    """Rodrigues: (3, 3) rotation of the rotation vector ``w`` (3,) radians (a kernel, so that
    the ICP iterations call it too; NumPy twin in tests/test_registration.py)."""
    out = np.eye(3)
    theta = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    if theta < 1e-12:
        return out
    kx = w[0] / theta
    ky = w[1] / theta
    kz = w[2] / theta
    K = np.array([[0.0, -kz, ky], [kz, 0.0, -kx], [-ky, kx, 0.0]])
    s = math.sin(theta)
    c = 1.0 - math.cos(theta)
    for a in range(3):
        for b in range(3):
            kk = K[a, 0] * K[0, b] + K[a, 1] * K[1, b] + K[a, 2] * K[2, b]
            out[a, b] += s * K[a, b] + c * kk
    return out
