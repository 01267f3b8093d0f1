"""The harsher depth noise models, beside sim_fixtures.noise's KinectNoise and GaussianNoise
(which the stored fixtures were made with, unchanged), and harsh-noise change scenes.

- :class:`RealisticKinectNoise`: the Kinect model fitted to real Xtion depth (SUN3D) with what
  KinectNoise lacks (noise correlated over the matching window, flicker, flying pixels, an
  error field per pose, registration to the colour camera with its zero border, true
  intrinsics that are not the nominal ones);
- :class:`StereoNoise`: an Intel RealSense D4xx-like active stereo camera;
- :func:`harsh_scene`: a stored scene's spec (its layouts, poses and truth) rendered again
  with RealisticKinectNoise, nothing stored.

Like the models of sim_fixtures.noise, each turns a :class:`~sim_fixtures.render.Render` into
a (H, W) uint16 depth image in millimetres (0 = no reading), deterministically given a
``numpy.random.Generator``.  ``bench/noise_real_vs_sim.py`` measures them against the real
recordings with ``sim_fixtures.real_noise``; ``noise.noise_from_json`` reads them back.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import zlib

import numpy as np

from sim_fixtures.noise import (
    _edge_band,
    kinect_axial_sigma,
    quantise_depth,
    to_millimetres,
)
from sim_fixtures.render import Render

__all__ = [
    "RealisticKinectNoise",
    "StereoNoise",
    "FITTED_NOTE",
    "HarshScene",
    "harsh_scene",
    "correlated_field",
    "fill_short_gaps",
    "register_to_colour",
    "true_camera_view",
]


def _pose_key(r: Render) -> int:
    """A 32-bit key of the render's camera pose (position to 1e-6 m, angles to 1e-6 deg)."""
    p = r.pose
    values = [*p.position, p.yaw_deg, p.pitch_deg, p.roll_deg]
    text = ",".join(f"{v:.6f}" for v in values)
    return zlib.crc32(text.encode())


@functools.lru_cache(maxsize=16)
def _spectral_filter(shape: tuple[int, int], kind: str, scale_px: float) -> np.ndarray:
    """rfft2 amplitude filter turning white noise into a stationary field: ``exp``: exponential
    covariance exp(-r / scale) (2-D spectrum (1 + (2 pi k scale)^2)^(-3/2)); ``gauss``: white
    noise smoothed by a Gaussian of std ``scale`` px."""
    h, w = shape
    ky = np.fft.fftfreq(h)[:, None]
    kx = np.fft.rfftfreq(w)[None, :]
    k2 = kx**2 + ky**2
    if kind == "exp":
        spectrum = (1.0 + (2 * math.pi * scale_px) ** 2 * k2) ** -1.5
    else:
        spectrum = np.exp(-4 * math.pi**2 * scale_px**2 * k2)
    return np.sqrt(spectrum)


def correlated_field(rng: np.random.Generator, shape: tuple[int, int], scale_px: float,
                     kind: str = "exp") -> np.ndarray:
    """(H, W) float64 stationary Gaussian field scaled to unit RMS over the image, correlated
    over ``scale_px`` (``kind`` 'exp': covariance exp(-r/scale); 'gauss': white noise smoothed
    by a Gaussian of std ``scale_px``); periodic at the image borders.  ``scale_px <= 0``:
    white noise."""
    white = rng.standard_normal(shape)
    if scale_px <= 0:
        return white
    field = np.fft.irfft2(np.fft.rfft2(white) * _spectral_filter(tuple(shape), kind,
                                                                 float(scale_px)), s=shape)
    return field / max(float(field.std()), 1e-12)


def _normal_cdf(x: np.ndarray) -> np.ndarray:
    """The standard normal CDF, erf by Abramowitz & Stegun 7.1.26 (error < 1.5e-7)."""
    y = np.abs(x) / math.sqrt(2.0)
    t = 1.0 / (1.0 + 0.3275911 * y)
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (
        -1.453152027 + t * 1.061405429))))
    erf = 1.0 - poly * np.exp(-y * y)
    return 0.5 * (1.0 + np.sign(x) * erf)


def _min_max_filter(z: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Min (of the hits, inf if none) and max of ``z`` (0 = no hit) over (2r+1)^2 windows."""
    zmin = np.where(z > 0, z, np.inf)
    zmax = z.copy()
    for axis in (0, 1):
        lo, hi = zmin.copy(), zmax.copy()
        for s in range(1, radius + 1):
            for sh in (s, -s):
                lo = np.minimum(lo, _shift(zmin, sh, axis, np.inf))
                hi = np.maximum(hi, _shift(zmax, sh, axis, 0.0))
        zmin, zmax = lo, hi
    return zmin, zmax


def _shift(a: np.ndarray, s: int, axis: int, fill: float) -> np.ndarray:
    """``a`` shifted by ``s`` along ``axis`` (out[i] = a[i - s]), ``fill`` where nothing comes."""
    out = np.full_like(a, fill)
    if axis == 0:
        if s > 0:
            out[s:] = a[:-s]
        else:
            out[:s] = a[-s:]
    else:
        if s > 0:
            out[:, s:] = a[:, :-s]
        else:
            out[:, :s] = a[:, -s:]
    return out


@dataclasses.dataclass(frozen=True)
class _View:
    """What the camera's pixels see: depth (m, 0 = nothing), incidence (rad), shadow."""

    depth: np.ndarray
    theta: np.ndarray
    shadow: np.ndarray


def _true_rays(intr, shape: tuple[int, int], f_scale: float, dcx_px: float, dcy_px: float,
               k1: float) -> tuple[np.ndarray, ...]:
    """The normalised rays (x, y) through the pixels of a camera with the true intrinsics of
    :func:`true_camera_view` and the nominal pixel (ui, vi) nearest each ray, ``inside``
    where that pixel lies in the image (elsewhere ui = vi = 0): (x, y, ui, vi, inside)."""
    h, w = shape
    u = np.arange(w, dtype=np.float64)[None, :]
    v = np.arange(h, dtype=np.float64)[:, None]
    xd = (u - (intr.cx + dcx_px)) / (intr.fx * f_scale) + 0 * v
    yd = (v - (intr.cy + dcy_px)) / (intr.fy * f_scale) + 0 * u
    x, y = xd.copy(), yd.copy()
    for _ in range(8):  # undistort: x (1 + k1 r^2) = x_d
        scale = 1.0 + k1 * (x * x + y * y)
        x, y = xd / scale, yd / scale
    un = np.rint(intr.fx * x + intr.cx).astype(np.int64)
    vn = np.rint(intr.fy * y + intr.cy).astype(np.int64)
    inside = (un >= 0) & (un < w) & (vn >= 0) & (vn < h)
    return x, y, np.where(inside, un, 0), np.where(inside, vn, 0), inside


def true_camera_view(r: Render, f_scale: float = 1.0, dcx_px: float = 0.0, dcy_px: float = 0.0,
                     k1: float = 0.0) -> _View:
    """The render as a camera whose true intrinsics differ from ``r.intrinsics`` (the nominal
    ones every consumer uses) would see it: focal lengths times ``f_scale``, principal point
    moved by (``dcx_px``, ``dcy_px``), radial distortion ``k1`` (x_d = x (1 + k1 r^2) in
    normalised coordinates) left in.  Pixel (u, v) shows the surface along the true ray
    through it: the nominal render's nearest pixel to that ray, its depth re-intersected with
    the plane of that pixel's surface (exact on planes; the neighbour's depth where the plane
    is near grazing or the change exceeds 5 %).  Rays leaving the render: no hit."""
    theta = np.arccos(np.clip(r.cos_incidence, 0.0, 1.0))
    if f_scale == 1.0 and dcx_px == 0.0 and dcy_px == 0.0 and k1 == 0.0:
        return _View(r.depth, theta, r.shadow)
    x, y, ui, vi, inside = _true_rays(r.intrinsics, r.depth.shape, f_scale, dcx_px, dcy_px, k1)
    p = r.points[vi, ui]
    n = r.normals[vi, ui]
    z0 = r.depth[vi, ui]
    hit = inside & (z0 > 0)
    nd = n[..., 0] * x + n[..., 1] * y + n[..., 2]
    npd = np.einsum("...i,...i->...", n, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = npd / nd
    ok = hit & (np.abs(nd) > 0.05) & np.isfinite(t) & (np.abs(t - z0) < 0.05 * z0)
    depth = np.where(hit, np.where(ok, t, z0), 0.0)
    return _View(depth, np.where(hit, theta[vi, ui], 0.0), hit & r.shadow[vi, ui])


def _scatter_nearest(target: np.ndarray, z: np.ndarray, size: int) -> np.ndarray:
    """(size,) int64: the index (into ``target`` / ``z``) of the smallest ``z`` landing on each
    flat ``target`` index, -1 where none lands."""
    out = np.full(size, -1, dtype=np.int64)
    if len(target) == 0:
        return out
    order = np.lexsort((z, target))
    t = target[order]
    first = np.ones(len(t), dtype=bool)
    first[1:] = t[1:] != t[:-1]
    out[t[first]] = order[first]
    return out


def register_to_colour(z: np.ndarray, valid: np.ndarray, fx: float, baseline_m: float,
                       fill_px: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Depth (m) as registered to a colour camera ``baseline_m`` to the right (+x) of the
    depth camera: forward-warped to the depth camera (u + fx b / z) and back (u - fx b / z),
    nearest pixel, the nearest surface winning.  ``z``: (H, W) the depth of every surface
    (0 = nothing), ``valid``: where the sensor has a reading (a pixel without one still hides
    what is behind it).  Returns (z, valid) on the colour grid.  What the depth camera
    cannot see beside near objects (a strip of fx b (1/z_near - 1/z_far) px on their right)
    gets no reading; strips up to ``fill_px`` wide take the farther side (the sensor fills
    them over its window), and rounding twice leaves the resampled, ragged edges of
    registered depth (one-pixel cracks in smooth surfaces are closed)."""
    h, w = z.shape
    if baseline_m == 0:
        return z, valid
    zz_all, ok_all = z.ravel(), valid.ravel()
    for sign in (1.0, -1.0):
        vv, uu = np.nonzero(zz_all.reshape(h, w) > 0)
        src = vv * w + uu
        zz = zz_all[src]
        u_new = np.rint(uu + sign * fx * baseline_m / zz).astype(np.int64)
        ok = (u_new >= 0) & (u_new < w)
        win = _scatter_nearest((vv * w + u_new)[ok], zz[ok], h * w)
        has = win >= 0
        pick = src[ok][np.where(has, win, 0)]
        zz_all = np.where(has, zz_all[pick], 0.0)
        ok_all = has & ok_all[pick]
    zr, vr = zz_all.reshape(h, w), ok_all.reshape(h, w)
    zr, vr = fill_short_gaps(zr, vr, fill_px)
    return _fill_cracks(zr, vr)


def _fill_cracks(z: np.ndarray, valid: np.ndarray, rel: float = 0.05
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Single-pixel gaps (no surface) between two surfaces within ``rel`` of each other (along
    a row, then a column) take the nearer one: the cracks that rounding a warp leaves in a
    smooth surface, which registered PrimeSense depth does not show (SUN3D: ~45 one-pixel
    holes in 271k readings)."""
    z, valid = z.copy(), valid.copy()
    for axis in (1, 0):
        a, b = _shift(z, 1, axis, 0.0), _shift(z, -1, axis, 0.0)
        va, vb = _shift(valid, 1, axis, False), _shift(valid, -1, axis, False)
        crack = (z == 0) & (a > 0) & (b > 0) & (np.abs(a - b) < rel * np.minimum(a, b))
        z = np.where(crack, np.minimum(a, b), z)
        valid = np.where(crack, np.where(a <= b, va, vb), valid)
    return z, valid


def _row_runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel of ``mask`` (H, W bool): the length of the horizontal run of True it lies in
    (0 outside), and the run's first column."""
    h, w = mask.shape
    flat = mask.ravel()
    start = flat.copy()
    start[1:] &= ~flat[:-1]
    start.reshape(h, w)[:, 0] = mask[:, 0]
    run = np.cumsum(start) - 1
    first_col = np.flatnonzero(start) % w
    lengths = np.bincount(run[flat], minlength=int(start.sum()))
    length = np.zeros(h * w, dtype=np.int64)
    first = np.zeros(h * w, dtype=np.int64)
    length[flat] = lengths[run[flat]]
    first[flat] = first_col[run[flat]]
    return length.reshape(h, w), first.reshape(h, w)


def fill_short_gaps(z: np.ndarray, valid: np.ndarray, max_px: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal runs of up to ``max_px`` pixels without a surface (z = 0), with one on both
    sides, take the farther side's depth and validity: the strips a warp uncovers beside near
    objects, narrower than the window a sensor fills them over."""
    if max_px <= 0:
        return z, valid
    h, w = z.shape
    length, first = _row_runs(z == 0)
    rows = np.arange(h)[:, None].repeat(w, axis=1)
    lc = np.maximum(first - 1, 0)
    rc = np.minimum(first + length, w - 1)
    left = np.where(first > 0, z[rows, lc], 0.0)
    right = np.where(first + length < w, z[rows, rc], 0.0)
    gap = (z == 0) & (length > 0) & (length <= max_px) & (left > 0) & (right > 0)
    far_left = left >= right
    z = np.where(gap, np.where(far_left, left, right), z)
    valid = np.where(gap, np.where(far_left, valid[rows, lc], valid[rows, rc]), valid)
    return z, valid


def _flying(z: np.ndarray, rel_jump: float, band_px: int, prob,
            u_fly: np.ndarray, u_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flying pixels: pixels within ``band_px`` of a depth jump (the (2 band + 1)^2 window's
    farthest hit beyond its nearest by more than ``rel_jump`` of it) read, with probability
    ``prob`` (a number, or a function of the window's foreground depth), a depth between the
    window's fore- and background: t in [0.1, 0.6] of the gap from the foreground on the
    foreground side, [0.4, 0.9] on the background side.  Returns the depths and the mask."""
    zmin, zmax = _min_max_filter(z, band_px)
    gap = zmax - zmin
    if callable(prob):
        prob = prob(np.where(np.isfinite(zmin), zmin, 0.0))
    at = (z > 0) & np.isfinite(zmin) & (gap > rel_jump * zmin) & (u_fly < prob)
    fg_side = (z - zmin) < (zmax - z)
    t = np.where(fg_side, 0.1 + 0.5 * u_t, 0.4 + 0.5 * u_t)
    out = np.where(at, zmin + t * np.where(np.isfinite(gap), gap, 0.0), z)
    return out, at


@dataclasses.dataclass(frozen=True)
class RealisticKinectNoise:
    """A harsher PrimeSense / Kinect v1 model, fitted to real Xtion depth (SUN3D study room).

    Everything :class:`KinectNoise` does (noise drawn before a quantisation in disparity,
    range, grazing drops, edge drops, projector shadows), re-fitted, plus what real
    PrimeSense depth shows and KinectNoise does not:

    - per-frame noise correlated over a few pixels (the 9x9 correlation window), so patches
      flip a disparity step together between frames (``noise_corr_px``: exponential
      covariance exp(-r / 4 px); ``noise_white_share`` of the variance white);
    - per-frame dropouts that flicker (valid in one frame, not in the next), in small blobs
      (``dropout``: p = ``dropout_at_4m`` (z / 4 m)^``dropout_exponent``, thresholding a field
      correlated over ``dropout_corr_px``);
    - flying pixels: a pixel within ``flying_band_px`` of a depth edge reads, with probability
      ``flying`` = ``flying_at_4m`` (z_near / 4 m)^``flying_exponent``, a depth between the
      two sides (0.1-0.6 of the gap from its own side);
    - a smooth error field on surfaces, RMS ``field_sigma_m_at_4m`` (z / 4 m)^
      ``field_exponent``, correlated over ``field_scale_px`` (Gaussian), fixed per camera
      pose and epoch: drawn from ``field_seed`` and the render's pose, so the same in every
      frame of one epoch and different between poses; :meth:`for_epoch` changes the seed
      (the slowly varying depth warping of PrimeSense sensors, Teichman, Miller & Thrun,
      "Unsupervised intrinsic calibration of depth sensors via SLAM", RSS 2013);
    - depth registered to a colour camera ``register_baseline_m`` to the right (Kinect: the
      RGB camera sits 2.5 cm from the IR camera, toward the projector): a round trip of
      forward warps leaves strips without depth on the right of near objects (strips up to
      ``register_fill_px`` wide are filled with the background), ragged resampled edges, and
      a zero border ``border_px`` (left, right, top, bottom);
    - true intrinsics that differ from the nominal ones the render (and every consumer) uses
      (focal x ``true_f_scale``, principal point moved by ``true_cx_offset_px`` /
      ``true_cy_offset_px``) and radial distortion ``k1`` left in (:func:`true_camera_view`).
    - shadows of the projector narrower than ``shadow_fill_px`` give readings (the window
      reads across them).

    Fitted to SUN3D (``bench/noise_real_vs_sim.py --fit``: its consecutive frames, their
    poses refined, against a study aisle rendered like it with the camera moved 1.5 cm; the
    procedure is that function's docstring; the figures below are the bench's final table):

    - ``quant_c_per_m`` 0.00292 /m: ``real_noise.fit_quant_c`` on all 50 frames (median gap /
      z^2 of the distinct depths; K&OE's 0.00285 for the Kinect);
    - per-frame sigma ``0.00321 + 0.00092 |z - 0.4|^2.5`` m: the simulated difference sigma
      per 0.5 m bin within 12 % of SUN3D's from 1 to 6 m (Nguyen's 0.0012 + 0.0019 (z -
      0.4)^2 gives 12-24 % less than SUN3D at 1-1.5 m and 4-5 m, within 15 % between);
    - ``noise_corr_px`` 4 (grid 2.5-5): correlation of the difference at 1 / 2 / 4 / 8 / 16
      px 0.65 / 0.50 / 0.31 / 0.12 / 0.02, SUN3D's 0.71 / 0.52 / 0.30 / 0.09 / 0.08
      (KinectNoise: 0);
    - grazing ramp 86-88 deg (grid of starts 86-80 deg; KinectNoise's 78-88 deg ramp and
      its edge drops make 4-15 % of the pixels at 3-5 m flicker, SUN3D 0.4-1.7 %);
    - dropout 0.61 % (z / 4 m)^3.5: flicker 0.15-2.5 % from 2 to 6 m against SUN3D's
      0.07-2.1 % (within 0.4 percentage points; SUN3D's 0.6-1.2 % at 1-2 m, around a
      chair's edges, is not reproduced);
    - flying pixels 0.06 (z / 4 m)^2 (grid of 0-0.5 and exponents 2-4 against SUN3D's
      share of in-between depths beside jumps per foreground depth: 0.4-0.6 % at 1-3 m, 5-8 %
      at 3.5-5 m, 23-38 % at 5-6 m; the geometry of the scene makes part of it, so
      SUN3D's crisp near edges leave little room);
    - error field 1.4 mm (z / 4 m)^4 over 40 px: the low-frequency difference SUN3D has
      beyond the correlated per-frame noise (2.5 mm at 2 m, 12-17 mm at 4-6 m in all;
      simulated 2.1-18.5 mm, within 25 % from 1.5 to 6 m);
    - ``register_fill_px`` 6 (grid 2-6; holes beside edges 4.6 %, SUN3D 1.9 %); edge drops 0
      (SUN3D's edges have fewer holes than the model has without them);
    - ``border_px`` (3, 37, 12, 7): SUN3D's zero border, measured (``real_noise.zero_border``).

    Chosen, not fitted: ``far_m`` 8 m (SUN3D's farthest reading is 7.0 m, its room's end);
    ``shadow_fill_px`` 4 (half the 9 px correlation window, Konolige & Mihelich's "Technical
    description of Kinect calibration"); ``register_baseline_m`` 2.5 cm (ibid.); the true
    intrinsics 1.5 % longer focal, principal point (+3, +8) px (per-device calibrations of
    Kinects differ from the nominal 525 / 319.5 / 239.5 by percents and up to ~15 px) and
    k1 = 0.05 (a small residual of the factory undistortion): SUN3D's pairs, 1.5-7.5 cm
    apart, hardly see these (the bench's k1 diagnostic).
    """

    near_m: float = 0.5
    far_m: float = 8.0
    quant_c_per_m: float = 0.00292
    axial_a_m: float = 0.00321
    axial_b_per_m: float = 0.00092
    axial_exponent: float = 2.5
    noise_corr_px: float = 4.0
    noise_white_share: float = 0.0
    grazing_start_deg: float = 86.0
    grazing_stop_deg: float = 88.0
    edge_rel_jump: float = 0.05
    edge_band_px: int = 1
    edge_drop_prob: float = 0.0
    projector_baseline_m: float = 0.075
    shadow_fill_px: int = 4
    dropout_at_4m: float = 0.0061
    dropout_exponent: float = 3.5
    dropout_corr_px: float = 2.0
    flying_at_4m: float = 0.06
    flying_exponent: float = 2.0
    flying_band_px: int = 1
    flying_rel_jump: float = 0.05
    field_sigma_m_at_4m: float = 0.0014
    field_exponent: float = 4.0
    field_scale_px: float = 40.0
    field_seed: int = 0
    register_baseline_m: float = 0.025
    register_fill_px: int = 6
    border_px: tuple[int, int, int, int] = (3, 37, 12, 7)
    true_f_scale: float = 1.015
    true_cx_offset_px: float = 3.0
    true_cy_offset_px: float = 8.0
    k1: float = 0.05

    kind = "kinect_realistic"

    def sigma(self, z: np.ndarray, theta: np.ndarray | float = 0.0) -> np.ndarray:
        """Per-frame std of the output (m) at depth ``z`` (m) and incidence ``theta`` (rad):
        ``axial_a + axial_b |z - 0.4|^axial_exponent`` plus Nguyen's angle term above 60
        degrees."""
        z = np.asarray(z, dtype=np.float64)
        angle = kinect_axial_sigma(z, theta) - (0.0012 + 0.0019 * (z - 0.4) ** 2)
        return self.axial_a_m + self.axial_b_per_m * np.abs(z - 0.4) ** self.axial_exponent \
            + angle

    def step(self, z: np.ndarray) -> np.ndarray:
        """Approximate quantisation step (m) at depth ``z`` (m): ``c z^2``."""
        return self.quant_c_per_m * np.asarray(z, dtype=np.float64) ** 2

    def dropout(self, z: np.ndarray) -> np.ndarray:
        """Per-frame probability that a pixel at depth ``z`` (m) gives no reading."""
        z = np.asarray(z, dtype=np.float64)
        return np.clip(self.dropout_at_4m * (z / 4.0) ** self.dropout_exponent, 0.0, 1.0)

    def flying(self, z: np.ndarray) -> np.ndarray:
        """Probability that a pixel beside a depth edge whose near side is at ``z`` (m) reads
        a depth between the two sides."""
        z = np.asarray(z, dtype=np.float64)
        return np.clip(self.flying_at_4m * (z / 4.0) ** self.flying_exponent, 0.0, 1.0)

    def field_sigma(self, z: np.ndarray) -> np.ndarray:
        """RMS (m) of the per-pose error field at depth ``z`` (m)."""
        z = np.asarray(z, dtype=np.float64)
        return self.field_sigma_m_at_4m * (z / 4.0) ** self.field_exponent

    def for_epoch(self, epoch: int) -> RealisticKinectNoise:
        """The same model with another error field (``field_seed = epoch``)."""
        return dataclasses.replace(self, field_seed=int(epoch))

    def field(self, r: Render) -> np.ndarray:
        """(H, W) unit-RMS smooth field of this epoch and the render's pose (cached)."""
        return _epoch_field(self.field_seed, _pose_key(r), r.depth.shape,
                            float(self.field_scale_px)).copy()

    def apply(self, r: Render, rng: np.random.Generator) -> np.ndarray:
        """One noisy frame of ``r``: (H, W) uint16 mm, 0 = no reading.

        ``r`` must be rendered with this model's ``projector_baseline_m`` for shadows to
        show.  Draws from ``rng`` in a fixed order (reproducible); the error field comes from
        ``field_seed`` and the pose, not from ``rng``.
        """
        view = true_camera_view(r, self.true_f_scale, self.true_cx_offset_px,
                                self.true_cy_offset_px, self.k1)
        z, theta, shadow = view.depth, view.theta, view.shadow
        if self.shadow_fill_px > 0:  # the correlation window reads across narrow shadows
            length, _ = _row_runs(shadow)
            shadow = shadow & (length > self.shadow_fill_px)
        shape = z.shape
        hit = z > 0
        # draws, always for every pixel and in this order
        corr = correlated_field(rng, shape, self.noise_corr_px)
        white = rng.standard_normal(shape)
        drop_field = correlated_field(rng, shape, self.dropout_corr_px)
        u_graze = rng.random(shape)
        u_edge = rng.random(shape)
        u_fly = rng.random(shape)
        u_t = rng.random(shape)
        ws = self.noise_white_share
        gauss = math.sqrt(1.0 - ws) * corr + math.sqrt(ws) * white
        edges = _edge_band(z, self.edge_rel_jump, self.edge_band_px)
        zf, flying = _flying(z, self.flying_rel_jump, self.flying_band_px, self.flying,
                             u_fly, u_t)
        sig = self.sigma(zf, theta)
        q = self.step(zf)
        sig_pre = np.sqrt(np.maximum(sig**2 - q**2 / 12.0, 0.0))
        offset = self.field_sigma(zf) * self.field(r) if self.field_sigma_m_at_4m else 0.0
        noisy = np.where(hit, zf + offset + sig_pre * gauss, 1.0)
        noisy = quantise_depth(np.maximum(noisy, 1e-3), self.quant_c_per_m)
        t_deg = np.degrees(theta)
        p_graze = np.clip(
            (t_deg - self.grazing_start_deg) / (self.grazing_stop_deg - self.grazing_start_deg),
            0.0, 1.0,
        )
        dropped = _normal_cdf(drop_field) < self.dropout(z)
        valid = (
            hit
            & ~shadow
            & (noisy >= self.near_m)
            & (noisy <= self.far_m)
            & (u_graze >= p_graze)
            & ~(edges & ~flying & (u_edge < self.edge_drop_prob))
            & ~dropped
        )
        surface = np.where(hit, np.where(valid, noisy, z), 0.0)
        out, valid = register_to_colour(surface, valid, r.intrinsics.fx,
                                        self.register_baseline_m, self.register_fill_px)
        left, right, top, bottom = self.border_px
        h, w = shape
        border = np.zeros(shape, dtype=bool)
        border[:, :left] = True
        border[:, w - right:] = right > 0
        border[:top] = True
        border[h - bottom:] = bottom > 0
        return to_millimetres(out, valid & (out > 0) & ~border)

    def to_json(self) -> dict:
        out = {"model": self.kind}
        out.update(dataclasses.asdict(self))
        out["border_px"] = list(self.border_px)
        out["fitted"] = FITTED_NOTE
        return out


@functools.lru_cache(maxsize=8)
def _epoch_field(seed: int, pose_key: int, shape: tuple[int, int], scale_px: float
                 ) -> np.ndarray:
    return correlated_field(np.random.default_rng([seed, pose_key, 7]), shape, scale_px,
                            "gauss")


#: How the RealisticKinectNoise defaults were obtained (also in its to_json).
FITTED_NOTE = ("fitted to SUN3D's study room (ASUS Xtion, consecutive frames) by "
               "bench/noise_real_vs_sim.py --fit; see RealisticKinectNoise's docstring and "
               "sim_fixtures/README.md")


@dataclasses.dataclass(frozen=True)
class StereoNoise:
    """Active stereo depth (Intel RealSense D4xx-like).

    - Depth RMS error, Intel's formula (Grunnet-Jepsen, Sweetser & Woodfill, "Tuning depth
      cameras for best performance", Intel RealSense white paper):
      ``sigma_z = z^2 * subpixel / (f * baseline)``, f the focal length in pixels, subpixel
      the RMS disparity error in pixels (0.08 is the paper's typical figure for a well
      textured scene; 0.05-0.1).  D435: baseline 50 mm; D455: 95 mm (Intel's datasheet).
      The noise is drawn in disparity, ``d = f b / z + N(0, subpixel^2)``, so the depth
      error grows with z^2.
    - Disparity quantised to 1/32 px (``disparity_step_px``: 5 fractional bits, our reading
      of Intel's description of the D4xx's subpixel disparity, not checked on a device), i.e.
      a depth step of ``z^2 / (32 f b)``.
    - Range: ``near_m`` / ``far_m``.  D435: min-Z about 0.28 m at 848x480 (Intel's
      datasheet), 0.3 m here; far 6 m, our cut (the formula's error there is ~2 % of the
      range at f = 424 px, 848x480; Intel quotes no hard maximum).  D455: min-Z about
      0.52 m (datasheet; 0.6 m here), far 10 m (our cut, the same ~2 % at f = 424 px).
    - Occlusion: the left imager is the depth camera, the right one sits ``baseline_m`` to its
      right (+x); surface points the right imager cannot see give no depth, a band beside
      near objects on their image-left.  Render with
      ``projector_baseline_m=noise.projector_baseline_m`` (the same ray-cast as a projector
      shadow).
    - Flying pixels at depth edges (block matching straddling the edge), ``flying_prob``
      within ``flying_band_px`` (our choice: no stereo recording here to fit it to).
    - ``f_px``: the focal length (pixels) of the formula; None: the render's fx.

    Invalid pixels on low-texture surfaces are not modelled (the projector textures them).
    """

    baseline_m: float = 0.050
    subpixel_px: float = 0.08
    disparity_step_px: float = 1.0 / 32.0
    near_m: float = 0.3
    far_m: float = 6.0
    flying_prob: float = 0.3
    flying_band_px: int = 1
    flying_rel_jump: float = 0.05
    f_px: float | None = None

    kind = "stereo"

    @classmethod
    def d435(cls, **kw) -> StereoNoise:
        """D435: 50 mm baseline, 0.3-6 m."""
        return cls(**{"baseline_m": 0.050, "near_m": 0.3, "far_m": 6.0, **kw})

    @classmethod
    def d455(cls, **kw) -> StereoNoise:
        """D455: 95 mm baseline, 0.6-10 m."""
        return cls(**{"baseline_m": 0.095, "near_m": 0.6, "far_m": 10.0, **kw})

    @property
    def projector_baseline_m(self) -> float:
        """The second imager's offset: render with this for the occlusion bands."""
        return self.baseline_m

    def _f(self, r_or_fx) -> float:
        if self.f_px is not None:
            return float(self.f_px)
        return float(r_or_fx.intrinsics.fx if hasattr(r_or_fx, "intrinsics") else r_or_fx)

    def sigma(self, z: np.ndarray, f_px: float) -> np.ndarray:
        """Depth RMS error (m) at ``z`` (m) for focal length ``f_px``: z^2 s / (f b)."""
        z = np.asarray(z, dtype=np.float64)
        return z**2 * self.subpixel_px / (self._f(f_px) * self.baseline_m)

    def step(self, z: np.ndarray, f_px: float) -> np.ndarray:
        """Depth step (m) of one disparity step at ``z``: z^2 dstep / (f b)."""
        z = np.asarray(z, dtype=np.float64)
        return z**2 * self.disparity_step_px / (self._f(f_px) * self.baseline_m)

    def apply(self, r: Render, rng: np.random.Generator) -> np.ndarray:
        """One noisy frame: (H, W) uint16 mm, 0 = no reading."""
        fb = self._f(r) * self.baseline_m
        z = r.depth
        shape = z.shape
        gauss = rng.standard_normal(shape)
        u_fly = rng.random(shape)
        u_t = rng.random(shape)
        hit = z > 0
        zf, _ = _flying(z, self.flying_rel_jump, self.flying_band_px, self.flying_prob,
                        u_fly, u_t)
        disp = np.where(hit, fb / np.where(hit, zf, 1.0), 0.0) + self.subpixel_px * gauss
        disp = np.rint(disp / self.disparity_step_px) * self.disparity_step_px
        ok = hit & (disp > 0) & ~r.shadow
        depth = np.where(ok, fb / np.where(disp > 0, disp, 1.0), 0.0)
        ok &= (depth >= self.near_m) & (depth <= self.far_m)
        return to_millimetres(depth, ok)

    def to_json(self) -> dict:
        out = {"model": self.kind}
        out.update(dataclasses.asdict(self))
        out["depth_rms"] = "z^2 subpixel / (f baseline), Intel RealSense white paper " \
            "(Grunnet-Jepsen et al., Tuning depth cameras for best performance)"
        return out


# ------------------------------------------------------------------------- harsh change scenes


@dataclasses.dataclass(frozen=True, eq=False)
class HarshScene:
    """A stored scene's spec rendered with the harsh Kinect model (:func:`harsh_scene`), with
    what the bench scores a stored :class:`sim_fixtures.Scene` by.  Frames: lists of (H, W)
    uint16 mm; ``changes`` as scene.json's (nominal renders).  ``truth_appeared``,
    ``observed_current``, ``ids_current`` (current image) and the reference's three: the ideal
    renders' masks as the true intrinsics see them (pixel (u, v) takes the nominal pixel its
    ray passes nearest, as the depth does; the colour registration moves edges <= 1 px more).
    """

    name: str
    seed: int
    split: str
    change: str
    changes: list
    reference: list
    current: list
    intrinsics: object
    T_ref_from_cur: np.ndarray
    truth_appeared: np.ndarray
    truth_disappeared: np.ndarray
    observed_reference: np.ndarray
    observed_current: np.ndarray
    ids_reference: np.ndarray
    ids_current: np.ndarray
    noise: object

    def reference_frames(self) -> list[np.ndarray]:
        return list(self.reference)

    def current_frames(self) -> list[np.ndarray]:
        return list(self.current)


def harsh_scene(name: str, seed: int = 0, noise: RealisticKinectNoise | None = None
                ) -> HarshScene:
    """The scene ``name`` (``sim_fixtures.scenes.get_spec``: its layouts, poses and truth;
    revisits included) rendered with ``noise`` (default ``RealisticKinectNoise()``) instead
    of its Kinect noise, ``spec.frames`` (3 + 3) frames.  Deterministic in its arguments,
    nothing stored; about 1-2 s on one core.  A Gaussian-noise scene (paper_sigma_*) raises
    ValueError.

    Reference frame k draws from ``default_rng([spec.seed, 0, k, 1000 + seed])``, current
    frame k from ``default_rng([spec.seed, spec.current_noise_epoch, k, 1000 + seed])``, each
    epoch with its own error field (``for_epoch(100000 seed + 100 spec.seed + stream)``), so a
    revisit shares its reference frames with the scene it revisits, as the stored ones do."""
    from sim_fixtures import scenes

    spec = scenes.get_spec(name)
    if spec.noise.kind != "kinect":
        raise ValueError(f"scene {name!r} has {spec.noise.kind} noise: harsh_scene re-renders "
                         "only the scenes with Kinect noise")
    noise = RealisticKinectNoise() if noise is None else noise
    spec = dataclasses.replace(spec, noise=noise)  # renders with its projector baseline
    ref, cur = scenes.render_pair(spec)
    appeared, disappeared = scenes.truth_masks(spec, ref, cur)
    seen_ref, seen_cur = scenes.observed_masks(spec, ref, cur)
    _, _, ui, vi, inside = _true_rays(spec.intrinsics, ref.depth.shape, noise.true_f_scale,
                                      noise.true_cx_offset_px, noise.true_cy_offset_px, noise.k1)

    def true(image):  # the nominal image as the true camera's pixels see it
        return np.where(inside, image[vi, ui], 0).astype(image.dtype)

    epochs = []
    for stream, r, count in ((0, ref, spec.frames[0]),
                             (spec.current_noise_epoch, cur, spec.frames[1])):
        model = noise.for_epoch(100000 * int(seed) + 100 * spec.seed + stream)
        epochs.append([model.apply(r, np.random.default_rng([spec.seed, stream, k,
                                                             1000 + int(seed)]))
                       for k in range(count)])
    return HarshScene(
        name, int(seed), spec.split, spec.change, scenes.change_geometry(spec, ref, cur),
        epochs[0], epochs[1], spec.intrinsics, scenes.true_transform(spec), true(appeared),
        true(disappeared), true(seen_ref), true(seen_cur), true(ref.ids), true(cur.ids), noise)
