"""A camera's noise measured from a still view: per-pixel statistics of N frames, the axial
sigma per depth bin, the quantisation step, flicker and edges (:func:`measure_frames`), and a
profile made of them (:func:`profile_from_frames`, ``robot-change calibrate``).

Every reference capture is measured the same way (robot_change.change.scene): its N fused frames
raise the configured profile where they are noisier
(:meth:`robot_change.noise.profile.NoiseProfile.raised_by`).
"""

from __future__ import annotations

import dataclasses
import datetime

import numpy as np
from scipy import ndimage

from robot_change.errors import InputError
from robot_change.noise.profile import NoiseProfile

__all__ = ["MAX_DRIFT", "FrameNoise", "drift_limit", "measure_frames", "profile_from_frames"]

#: Depth bins of the measurement: BIN_M wide from MIN_BIN_M; a bin needs MIN_BIN_PIXELS
#: pixels read in every frame, off any edge, to be kept.
BIN_M = 0.25
MIN_BIN_M = 0.25
MAX_BIN_M = 10.0
MIN_BIN_PIXELS = 200
#: A depth edge: neighbouring readings apart by more than this share of the depth (5 %: a
#: surface tilted 87 degrees from the ray, at a Kinect's angular resolution).
EDGE_REL_JUMP = 0.05


#: A :attr:`FrameNoise.drift` above :func:`drift_limit` says the view moved steadily, which
#: per-pixel variances take for noise (calibrate refuses it; a capture says so).  Still views
#: measure 0.98-1.01 (rendered Kinect and RealisticKinect noise, 3 to 30 frames); the SUN3D
#: Xtion carried by hand, ~1 cm a frame: 1.62-1.89 over 3 frames, 2.27-2.69 over 4, 2.2-3.5
#: over 5, 9.1 over 30 (sigma 15-20 times the Xtion's); PCL's grabber frames, hand-held 3-10
#: mm apart: 1.62 over 3 (sigma 17 times the Kinect's).  A drift under a tenth of one
#: reading's sigma a frame stays under MAX_DRIFT over 30 frames (simulated: 2.58 at a tenth)
#: and adds up to a third to sigma.
MAX_DRIFT = 2.5


def drift_limit(frames: int) -> float:
    """The largest drift of a still view over ``frames`` frames: half their number (steady
    motion drifts towards frames - 1, noise stays at 1), at most :data:`MAX_DRIFT`; two frames
    cannot tell (their drift is 1 by definition)."""
    return min(MAX_DRIFT, frames / 2.0) if frames >= 3 else float("inf")


@dataclasses.dataclass(frozen=True)
class FrameNoise:
    """What N frames of a still camera show of its noise.

    ``bins``: ((depth bin centre m, sigma m, pixels), ...), sigma the root mean of the
    per-pixel variances over the pixels of the bin read in every frame and off any edge;
    ``step_per_m``: the quantisation step over z^2 (median gap between distinct readings of a
    bin over z^2; 0 where the readings are millimetres apart); ``flicker_valid``: the share of
    pixels with a reading in one frame and none in the next (of those with a reading in
    either); ``flicker_step``: the share of pixels read in both whose reading moved by at
    least one quantisation step (a whole step; readings 1 mm apart count at 2 mm);
    ``edge_px``: how far from a depth edge readings still lie between the two surfaces
    (flying pixels), pixels; ``flying_share``: the share of pixels next to an edge that do;
    ``drift``: how far the last frame lies from the first against how far each lies from the
    one before (mean absolute differences over the pixels read in every frame, off any edge):
    1 where the frames differ by noise alone, whatever their number; a camera or scene that
    moves steadily takes it towards N - 1 (the per-pixel variances then hold the motion).
    """

    n_frames: int
    bins: tuple[tuple[float, float, int], ...]
    step_per_m: float
    flicker_valid: float
    flicker_step: float
    edge_px: int
    flying_share: float
    drift: float

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        out["bins"] = [[round(z, 3), round(s, 5), n] for z, s, n in self.bins]
        return out


def _as_stack(frames) -> np.ndarray:
    stack = np.asarray(frames)
    if stack.ndim != 3 or stack.dtype != np.uint16 or stack.shape[0] < 2:
        raise InputError(f"measuring noise needs at least 2 depth frames (N, H, W) uint16 mm, got "
                         f"{stack.dtype} {stack.shape}")
    return stack


def _edges(depth: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels with a neighbour (4-neighbourhood) whose reading is farther or
    nearer by more than EDGE_REL_JUMP of the depth, or without a reading."""
    d = depth.astype(np.float64)
    edge = np.zeros(d.shape, bool)
    for axis in (0, 1):
        a, b = (np.take(d, range(0, d.shape[axis] - 1), axis=axis),
                np.take(d, range(1, d.shape[axis]), axis=axis))
        jump = (np.abs(a - b) > EDGE_REL_JUMP * np.maximum(a, b)) | (a == 0) | (b == 0)
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        edge[tuple(lo)] |= jump
        edge[tuple(hi)] |= jump
    return edge


def _step_per_m(values_mm: np.ndarray, z: float) -> float:
    """The quantisation step over z^2 from the distinct readings (mm) of one depth bin: the
    median gap between neighbouring distinct values (0 when they are 1-2 mm apart)."""
    distinct = np.unique(values_mm)
    if distinct.size < 3:
        return 0.0
    gap = float(np.median(np.diff(distinct))) * 1e-3
    return gap / (z * z) if gap > 0.0025 else 0.0


def _flying(median: np.ndarray) -> tuple[int, float]:
    """(band width px, share): how far from a depth edge of the median image readings lie
    between the near and the far surface there (by more than 20 % of the jump from both),
    and the share of pixels next to an edge that do."""
    d = median.astype(np.float64)
    w = d.shape[1]
    width = 0
    share = 0.0
    for px in (1, 2, 3, 4):
        between = np.zeros(d.shape, bool)
        near_edge = np.zeros(d.shape, bool)
        # along rows: the readings px apart on either side of a pixel
        left, right = d[:, :w - 2 * px], d[:, 2 * px:]
        mid = d[:, px:w - px]
        ok = (left > 0) & (right > 0) & (mid > 0)
        lo, hi = np.minimum(left, right), np.maximum(left, right)
        jump = ok & (hi - lo > EDGE_REL_JUMP * hi)
        gap = hi - lo
        inside = jump & (mid > lo + 0.2 * gap) & (mid < hi - 0.2 * gap)
        between[:, px:w - px] = inside
        near_edge[:, px:w - px] = jump
        n = int(near_edge.sum())
        if n == 0:
            break
        s = float(between.sum()) / n
        if px == 1:
            share = s
        if s < 0.02:
            break
        width = px
    return width, share


def measure_frames(frames) -> FrameNoise:
    """The noise of a still camera from its frames ((N, H, W) uint16 mm, N >= 2, or a list of
    such images): :class:`FrameNoise`.  Raises :class:`InputError` for fewer than 2 frames or
    another dtype."""
    stack = _as_stack(frames)
    n = stack.shape[0]
    # per-pixel mean (mm) and variance (m^2) from exact sums of the readings (mm, mm^2) taken
    # frame by frame: the memory of a few images, whatever the number of frames; a pixel
    # whose mean lies on a bin's edge falls in the upper bin
    total = np.zeros(stack.shape[1:], np.int64)
    squares = np.zeros(stack.shape[1:], np.int64)
    all_valid = np.ones(stack.shape[1:], bool)
    for k in range(n):
        mm = stack[k].astype(np.int64)
        total += mm
        squares += mm * mm
        all_valid &= mm > 0
    mean_mm = total / n
    var = (squares - total * total / n) / (n - 1) * 1e-6
    median = np.median(stack, axis=0).astype(np.uint16)
    edge = ndimage.binary_dilation(_edges(median), iterations=2)  # 4-neighbourhood, 2 px
    use = all_valid & ~edge
    bins = []
    steps = []
    lo = MIN_BIN_M
    while lo < MAX_BIN_M:
        sel = use & (mean_mm >= lo * 1000) & (mean_mm < (lo + BIN_M) * 1000)
        count = int(sel.sum())
        if count >= MIN_BIN_PIXELS:
            z = lo + BIN_M / 2
            bins.append((z, float(np.sqrt(var[sel].mean())), count))
            steps.append(_step_per_m(stack[0][sel], z))
        lo += BIN_M
    step = float(np.median(steps)) if steps else 0.0
    toggles = either = jumped = compared = 0
    consecutive = 0.0  # summed |frame k - frame k-1| over the pixels used, mm
    for k in range(1, n):  # consecutive frames, a pair at a time
        before, after = stack[k - 1], stack[k]
        was, now = before > 0, after > 0
        toggles += int(np.count_nonzero(was ^ now))
        either += int(np.count_nonzero(was | now))
        both = was & now & ~edge
        z = after * 1e-3
        whole_step = np.maximum(step * z * z, 0.002)
        moved = np.abs(z - before * 1e-3) >= 0.999 * whole_step
        jumped += int(np.count_nonzero(moved & both))
        compared += int(np.count_nonzero(both))
        consecutive += float(np.abs(after[use].astype(np.int64) - before[use]).sum())
    first_to_last = float(np.abs(stack[-1][use].astype(np.int64) - stack[0][use]).sum())
    edge_px, flying = _flying(median)
    return FrameNoise(
        n_frames=n, bins=tuple(bins), step_per_m=step,
        flicker_valid=float(toggles / max(either, 1)),
        flicker_step=float(jumped / max(compared, 1)), edge_px=edge_px, flying_share=flying,
        drift=first_to_last * (n - 1) / consecutive if consecutive > 0 else 0.0)


def profile_from_frames(frames, base: NoiseProfile, source: str) -> tuple[NoiseProfile,
                                                                           FrameNoise]:
    """A measured camera profile (``robot-change calibrate``): ``base``'s principle, range and
    shadow baseline, sigma the measured bins (``base``'s shape, scaled to meet them, beyond
    the measured depths), the measured step, flicker and edge figures.  Returns (profile, the
    measurement).  Raises :class:`InputError` when no depth bin has enough readings."""
    noise = measure_frames(frames)
    if not noise.bins:
        raise InputError(f"{source}: no depth between {MIN_BIN_M} and {MAX_BIN_M} m was read in "
                         f"every frame over {MIN_BIN_PIXELS} pixels; point the camera at a "
                         "still scene within its range")
    when = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    said = f"{noise.n_frames} frames of {source} at {when}"
    profile = base.replaced_by(
        noise.bins, f"measured: {said} (the built-in {base.name} gives the principle, the "
        "range and sigma's shape beyond the measured depths)",
        flicker_valid=noise.flicker_valid, flicker_step=noise.flicker_step,
        step_per_m=noise.step_per_m if base.step_per_m > 0 else 0.0,
        edge_px=max(noise.edge_px, 1))
    return profile, noise
