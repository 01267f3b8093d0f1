"""Warm-up: compile (or load from the numba cache) the kernels before the daemon says READY."""

from __future__ import annotations

import time

import numpy as np

from hw.depth import Intrinsics
from robot_change.change.detect import detect_changes
from robot_change.change.scene import build_scene
from robot_change.errors import EmptySceneError, InputError
from robot_change.service.config import Config
from robot_change.service.params import change_params

__all__ = ["warm_up"]


def _synthetic_room(width: int = 160, height: int = 120, box: bool = False) -> np.ndarray:
    """A small synthetic depth image: floor, back wall, a side wall, optionally a box."""
    cam = Intrinsics.openni_default(width, height)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    x = (u - cam.cx) / cam.fx
    y = (v - cam.cy) / cam.fy
    z = np.full((height, width), 3.0)  # back wall 3 m ahead
    floor = np.where(y > 1e-6, 1.0 / np.maximum(y, 1e-6), np.inf)  # floor 1 m below the camera
    z = np.minimum(z, floor)
    side = np.where(x > 1e-6, 1.2 / np.maximum(x, 1e-6), np.inf)  # wall 1.2 m to the right
    z = np.minimum(z, side)
    if box:
        px, py = x * 2.0, y * 2.0  # a 40 cm box standing 2 m ahead
        inside = (np.abs(px + 0.2) < 0.2) & (py > 0.6) & (py < 1.0)
        z = np.where(inside, np.minimum(z, 2.0), z)
    ripple = 0.002 * np.sin(u * 0.7) * np.cos(v * 0.5)
    return np.clip((z + ripple) * 1000.0, 0, 65535).astype(np.uint16)


def warm_up(config: Config | None = None) -> float:
    """Compile (or load from the numba cache) every kernel a capture and a check use, on a tiny
    synthetic scene; returns the seconds it took."""
    config = config or Config()
    t0 = time.perf_counter()
    width, height = 160, 120
    cam = Intrinsics.openni_default(width, height)
    params = config.scene_params()
    # regions of any size, and any registration taken as at the station, so that every stage
    # runs on the tiny scene (both directions; the box is a large share of it)
    change = change_params(config, config.parameters()).replace(min_region_points=1)
    change = change.replace(registration=change.registration.replace(
        min_fitness=0.0, max_seen_through=1.0, max_translation_m=100.0,
        max_rotation_deg=180.0))
    # a transform taken as given (registration off): the comparison through a transform
    shifted = change.replace(registration=change.registration.replace(enabled=False))
    offset = np.eye(4)
    offset[:3, 3] = (0.01, 0.0, 0.0)
    rooms = (_synthetic_room(width, height), _synthetic_room(width, height, box=True))
    for before, after in (rooms, rooms[::-1]):
        try:
            reference = build_scene(np.stack([before] * 2), params, intrinsics=cam,
                                    source="warm-up")
            detect_changes(reference, after, change)
            detect_changes(reference, after, shifted, initial_pose=offset)
        except (EmptySceneError, InputError):
            pass  # a tiny scene may be too small for some parameter set; kernels ran anyway
    # the table-plane starts' kernel runs on table tops only (not on the synthetic room)
    from robot_change.change import registration
    registration._plane_grid(np.zeros((2, 2, 3)), np.eye(3), np.zeros(3), 0.02, 0.0, 0.0, 8, 8,
                             0.015, 0.03)
    return time.perf_counter() - t0
