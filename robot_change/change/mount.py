"""Where the camera sits on the robot, and results in the robot's base frame (REP 103).

Everything the method computes is in the camera's optical frame (x right, y down, z forward).
A base controller thinks in ``base_link`` (x forward, y left, z up).  :class:`CameraMount` is
the camera's pose on the base: the pose of its *body* frame (``camera_link``: x forward, y
left, z up, the ROS convention) in ``base_link``, as a translation (m) and roll / pitch / yaw
(degrees, ``R = Rz(yaw) Ry(pitch) Rx(roll)``).  The optical frame is fixed to the body frame by
REP 103.  The default, all zeros, is a camera at the base origin looking straight ahead.

Numeric module: arrays in, arrays out.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import numpy as np

from robot_change import validate
from robot_change.change.registration import (
    Registration,
    invert,
    rotation_to_rpy_deg,
    rpy_deg_to_rotation,
)
from robot_change.errors import InputError

__all__ = ["BODY_FROM_OPTICAL", "CameraMount", "BaseOffset"]

#: (3, 3) rotation optical -> body (REP 103): columns are the optical x (right), y (down) and
#: z (forward) axes in the body frame (x forward, y left, z up).
BODY_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])

_num = functools.partial(validate.number, "CameraMount")


@dataclasses.dataclass(frozen=True)
class BaseOffset:
    """How far the robot stands from its station pose, in the station pose's base frame.

    ``translation_m`` (3,) x forward, y left, z up; ``rpy_deg`` (3,) roll, pitch, yaw;
    ``weak``: base-frame directions the views leave unconstrained ("x", "y", "z", "roll",
    "pitch", "yaw").
    """

    translation_m: tuple[float, float, float]
    rpy_deg: tuple[float, float, float]
    weak: tuple[str, ...]

    def to_dict(self) -> dict:
        return {"translation_m": [round(v, 5) for v in self.translation_m],
                "rpy_deg": [round(v, 4) for v in self.rpy_deg],
                "weak_directions": list(self.weak)}


@dataclasses.dataclass(frozen=True)
class CameraMount:
    """The camera's body frame in ``base_link``: ``xyz_m`` (3,) metres, ``rpy_deg`` (3,)."""

    xyz_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        for name, limit, unit in (("xyz_m", 10.0, " metres"), ("rpy_deg", 180.0, " degrees")):
            value = getattr(self, name)
            if not isinstance(value, (tuple, list)) or len(value) != 3:
                raise InputError(f"CameraMount.{name}={value!r}: must be 3 numbers")
            object.__setattr__(self, name, tuple(_num(name, v, -limit, limit, unit=unit)
                                                 for v in value))

    @classmethod
    def parse(cls, text: str) -> CameraMount:
        """From ``"x,y,z,roll,pitch,yaw"`` (metres, degrees), as the CLI's ``--mount`` takes."""
        try:
            values = [float(v) for v in str(text).split(",")]
        except ValueError:
            values = []
        if len(values) != 6 or not all(math.isfinite(v) for v in values):
            raise InputError(f"mount {text!r}: expected six numbers x,y,z,roll,pitch,yaw "
                             f"(metres, degrees), e.g. 0.2,0,0.45,0,10,0")
        return cls(tuple(values[:3]), tuple(values[3:]))  # type: ignore[arg-type]

    def base_from_optical(self) -> np.ndarray:
        """(4, 4) float64: optical-frame points -> base_link."""
        out = np.eye(4)
        out[:3, :3] = rpy_deg_to_rotation(*self.rpy_deg) @ BODY_FROM_OPTICAL
        out[:3, 3] = self.xyz_m
        return out

    def to_base(self, points: np.ndarray) -> np.ndarray:
        """(M, 3) optical-frame points -> (M, 3) float64 base-frame points."""
        B = self.base_from_optical()
        return np.asarray(points, dtype=np.float64).reshape(-1, 3) @ B[:3, :3].T + B[:3, 3]

    def offset(self, registration: Registration) -> BaseOffset:
        """The robot's pose now relative to its pose at the reference, in the station pose's
        base frame: ``B T_ref_from_cur B^-1`` with ``B`` = :meth:`base_from_optical`."""
        B = self.base_from_optical()
        T = B @ registration.T_ref_from_cur @ invert(B)
        weak = []
        optical_axes = {"x": 0, "y": 1, "z": 2}
        for name in registration.weak:
            rot = name.startswith("rot_")
            axis = np.zeros(3)
            axis[optical_axes[name[-1]]] = 1.0
            k = int(np.argmax(np.abs(B[:3, :3] @ axis)))
            label = ("roll", "pitch", "yaw")[k] if rot else "xyz"[k]
            if label not in weak:
                weak.append(label)
        return BaseOffset(tuple(float(v) for v in T[:3, 3]),  # type: ignore[arg-type]
                          tuple(float(v) for v in rotation_to_rpy_deg(T[:3, :3])),
                          tuple(weak))

    def to_dict(self) -> dict[str, Any]:
        return {"xyz_m": list(self.xyz_m), "rpy_deg": list(self.rpy_deg),
                "frame": "camera body frame (x forward, y left, z up) in base_link"}
