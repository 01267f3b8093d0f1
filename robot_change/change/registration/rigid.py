"""Rigid transforms of the camera frames: (4, 4) float64 matrices, metres, angles in degrees
unless said."""

from __future__ import annotations

import math

import numpy as np


def invert(T: np.ndarray) -> np.ndarray:
    """(4, 4) inverse of a rigid transform."""
    out = np.eye(4)
    R = T[:3, :3]
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(M, 3) float32 ``points`` mapped by the (4, 4) rigid transform ``T``."""
    p = np.asarray(points, dtype=np.float64)
    return (p @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of the rotation matrix ``R`` (3, 3), degrees."""
    c = (float(np.trace(R)) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


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


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rodrigues: (3, 3) rotation of the rotation vector ``w`` (radians)."""
    theta = float(np.linalg.norm(w))
    if theta < 1e-12:
        return np.eye(3)
    k = w / theta
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * K + (1.0 - math.cos(theta)) * (K @ K)
