"""``robot-change calibrate``: a camera's noise measured from a still view, written as the
profile file the configuration's ``[camera] profile_file`` names (robot_change.noise).

The camera must stand still before a scene that does not move, for the few seconds of frames
read; what moves between them is taken for noise.  The measured sigma per depth bin replaces
the built-in profile's where it was measured (the built-in's shape carries it beyond), with the
measured quantisation step, flicker and edge figures.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from hw.depth import DepthSource
from robot_change.errors import InputError
from robot_change.noise.estimate import FrameNoise, drift_limit, profile_from_frames
from robot_change.noise.profile import NoiseProfile

log = logging.getLogger(__name__)

__all__ = ["calibrate", "calibration_summary"]

#: A measurement this many times noisier than the built-in profile at 1-3 m says the camera or
#: the scene moved rather than that the camera is that noisy: refused.
MOVED_FACTOR = 20.0


def calibrate(source: DepthSource, base: NoiseProfile, out: Path, frames: int = 30,
              timeout: float = 2.0) -> tuple[NoiseProfile, FrameNoise, float]:
    """Read ``frames`` frames of ``source`` (opened here, closed by its owner), measure them
    against the built-in ``base`` and write the profile to ``out``.  Returns (the profile, the
    measurement, seconds spent).  Raises :class:`InputError` when fewer than 2 frames come,
    when they are all the same frame, when no depth is read in every frame, or when the frames
    differ so much that the camera or the scene moved."""
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 2:
        raise InputError(f"frames={frames!r}: calibrating measures how frames of a still view "
                         "differ, so it needs at least 2 (30 by default: a second at 30 fps)")
    t0 = time.perf_counter()
    source.open()
    stack = []
    while len(stack) < frames:
        frame = source.read(timeout=timeout)
        if frame is None:
            break
        stack.append(frame.depth)
    uri = getattr(source, "uri", "") or "the camera"
    if len(stack) < 2:
        raise InputError(f"{uri}: {len(stack)} frame(s) read; calibrating needs at least 2 of "
                         "a still view (a recording that ended, or a camera that stopped?)")
    if len(stack) < frames:
        log.warning("%s ended after %d of the %d frames asked for: the profile is measured on "
                    "%d (its flicker and steps are rough from few frames)", uri, len(stack),
                    frames, len(stack))
    if all(np.array_equal(stack[0], depth) for depth in stack[1:]):
        raise InputError(f"{uri}: the {len(stack)} frames are identical, so there is no noise "
                         "to measure (one image or frame looped, or a camera repeating its "
                         "last frame); calibrate on the camera's own frames of a still view")
    profile, noise = profile_from_frames(np.stack(stack), base, uri)
    near = [s / float(base.sigma(z)) for z, s, _ in noise.bins if 1.0 <= z <= 3.0]
    if near and float(np.median(near)) > MOVED_FACTOR:
        raise InputError(f"{uri}: the frames differ {float(np.median(near)):.0f} times more "
                         f"than a {base.name} camera's noise at 1-3 m: the camera or the scene "
                         "moved while they were read; keep both still and calibrate again")
    if noise.drift > drift_limit(noise.n_frames):
        raise InputError(f"{uri}: the last frame lies {noise.drift:.1f} times as far from the "
                         f"first as frames from the one before (noise alone: about 1): the "
                         f"camera or the scene moved steadily while they were read; keep both "
                         f"still and calibrate again")
    profile.save(out)
    return profile, noise, time.perf_counter() - t0


def calibration_summary(profile: NoiseProfile, base: NoiseProfile, noise: FrameNoise,
                        seconds: float, out: Path) -> dict[str, Any]:
    """What ``calibrate`` prints: the file, the measurement per depth bin against the
    built-in's sigma, the step, flicker and edge figures."""
    return {
        "file": str(out), "profile": profile.name, "frames": noise.n_frames,
        "seconds": round(seconds, 2),
        "bins": [{"depth_m": round(z, 3), "sigma_mm": round(s * 1000, 2), "pixels": n,
                  "builtin_sigma_mm": round(float(base.sigma(z)) * 1000, 2)}
                 for z, s, n in noise.bins],
        "step_per_m": round(noise.step_per_m, 6), "flicker_valid": round(noise.flicker_valid, 4),
        "flicker_step": round(noise.flicker_step, 4), "edge_px": noise.edge_px,
        "flying_share": round(noise.flying_share, 4), "drift": round(noise.drift, 3),
    }
