"""Statistics of depth noise measured on frame pairs, the same for real and simulated depth.

A *pair* is two depth images of a static scene, ``(depth_a, depth_b, T_b_from_a, intrinsics)``:
(H, W) uint16 mm (0 = no reading), the rigid transform (4, 4) mapping camera-a points into
camera b (the identity for a camera that did not move) and the pinhole intrinsics (an
``hw.depth.Intrinsics`` or ``(fx, fy, cx, cy)``).  Every valid pixel of a is back-projected,
moved by ``T_b_from_a`` and projected into b (nearest pixel, the nearest point winning where
several land on one pixel); its *difference* is ``depth_b[landing] - z_predicted`` (metres).

:func:`pair_stats` pools pairs and gives per depth bin (of the predicted depth; 0.5 m bins from
0.5 to 6 m by default) the robust sigma (1.4826 MAD) and the 99 / 99.9 % quantiles of |d|, the
quantisation step (median gap between distinct depth values of the bin), the flicker rate
(landing pixels valid in one frame and not in the other), the whole-step rate (|d| rounds to one
or more quantisation steps) and the sigma of the low-frequency part of d (a box mean over
``lowfreq_px``, the spatially correlated error).  :func:`edge_stats` measures one image's depth
edges: the share of pixels within 1-2 px of a discontinuity whose depth lies between the fore-
and background (flying pixels) and the width of that band.  :func:`refine_pose` improves a pose
by point-to-plane alignment (SUN3D's poses are good to ~1 cm, which is more than the noise).

:func:`harsh_pairs` generates NO-CHANGE pairs of the stored room layouts with the harsh Kinect
model (``harsh_noise.RealisticKinectNoise``), not stored on disk.

NumPy only (and ``hw.depth.Intrinsics``); nothing here imports robot_change.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Sequence

import numpy as np

__all__ = [
    "DEFAULT_BINS_M",
    "PairStats",
    "EdgeStats",
    "as_fxfycxcy",
    "back_project",
    "landing",
    "refine_pose",
    "zero_border",
    "quantisation_step",
    "pair_stats",
    "edge_stats",
    "fit_quant_c",
    "HarshPair",
    "harsh_pairs",
]

#: Depth bins (metres) of the statistics: 0.5 m wide from 0.5 to 6 m.
DEFAULT_BINS_M = np.round(np.arange(0.5, 6.01, 0.5), 6)
#: Lags (px) of the difference's spatial correlation, and the depths (m) it is taken over.
CORR_LAGS = (1, 2, 4, 8, 16)
CORR_RANGE_M = (1.5, 5.0)


def as_fxfycxcy(intrinsics) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` of an ``hw.depth.Intrinsics`` or a 4-sequence."""
    if hasattr(intrinsics, "fx"):
        return (float(intrinsics.fx), float(intrinsics.fy), float(intrinsics.cx),
                float(intrinsics.cy))
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    return fx, fy, cx, cy


def back_project(depth: np.ndarray, intrinsics) -> np.ndarray:
    """(H, W) uint16 mm -> (H, W, 3) float64 camera points (m); 0 where no reading."""
    fx, fy, cx, cy = as_fxfycxcy(intrinsics)
    h, w = depth.shape
    z = depth.astype(np.float64) / 1000.0
    u = np.arange(w, dtype=np.float64)[None, :]
    v = np.arange(h, dtype=np.float64)[:, None]
    return np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=-1)


def _project(q: np.ndarray, camera: tuple[float, float, float, float], w: int, h: int):
    """Points ``q`` (N, 3) (m, camera frame) onto a ``w`` x ``h`` image of ``camera`` (fx, fy,
    cx, cy): (u, v) (N,) int64 pixels, the depth (N,) (1 where behind the camera), and (N,) bool
    whether each lands in front of the camera and inside the image."""
    fx, fy, cx, cy = camera
    ok = q[:, 2] > 1e-3
    zq = np.where(ok, q[:, 2], 1.0)
    u = np.floor(fx * q[:, 0] / zq + cx + 0.5).astype(np.int64)
    v = np.floor(fy * q[:, 1] / zq + cy + 0.5).astype(np.int64)
    ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    return u, v, zq, ok


def landing(depth_a: np.ndarray, T_b_from_a: np.ndarray, intrinsics,
            shape_b: tuple[int, int] | None = None) -> dict:
    """Where each valid pixel of ``depth_a`` lands in camera b.

    Returns a dict of 1-D arrays over the landed pixels: ``src`` (flat index in a), ``dst``
    (flat index in b), ``z_pred`` (m, the point's depth in camera b), ``z_a`` (m).  Pixels that
    land outside b's image or behind it are left out; where several land on one pixel of b the
    nearest is kept (a z-buffer).
    """
    fx, fy, cx, cy = as_fxfycxcy(intrinsics)
    h, w = shape_b or depth_a.shape
    pts = back_project(depth_a, intrinsics).reshape(-1, 3)
    src = np.flatnonzero(depth_a.ravel() > 0)
    p = pts[src]
    T = np.asarray(T_b_from_a, dtype=np.float64)
    u, v, zq, ok = _project(p @ T[:3, :3].T + T[:3, 3], (fx, fy, cx, cy), w, h)
    src, zq, dst = src[ok], zq[ok], (v * w + u)[ok]
    order = np.lexsort((zq, dst))  # by landing pixel, nearest first
    dst_sorted = dst[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = dst_sorted[1:] != dst_sorted[:-1]
    keep = order[first]
    return {"src": src[keep], "dst": dst[keep], "z_pred": zq[keep],
            "z_a": p[ok][keep][:, 2] if len(keep) else np.zeros(0)}


def _normals(points: np.ndarray) -> np.ndarray:
    """(H, W, 3) points -> (H, W, 3) unit normals from central differences (0 where unknown)."""
    valid = points[..., 2] > 0
    n = np.zeros_like(points)
    dx = points[1:-1, 2:] - points[1:-1, :-2]
    dy = points[2:, 1:-1] - points[:-2, 1:-1]
    ok = valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1] & valid[1:-1, 1:-1]
    c = np.cross(dx, dy)
    norm = np.linalg.norm(c, axis=-1)
    z = points[1:-1, 1:-1, 2]
    # reject normals across depth jumps: neighbour spread > 5 % of the depth
    spread = np.maximum(np.abs(dx[..., 2]), np.abs(dy[..., 2]))
    ok &= (norm > 0) & (spread < 0.05 * np.maximum(z, 1e-6) + 0.02)
    c = c / np.where(norm > 0, norm, 1.0)[..., None]
    n[1:-1, 1:-1] = np.where(ok[..., None], c, 0.0)
    return n


def _se3_exp(xi: np.ndarray) -> np.ndarray:
    """(6,) (rx, ry, rz, tx, ty, tz) -> (4, 4), small-angle exact via Rodrigues."""
    w, t = xi[:3], xi[3:]
    th = float(np.linalg.norm(w))
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        R = np.eye(3) + K
    else:
        R = np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th**2 * K @ K
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = t
    return out


def refine_pose(depth_a: np.ndarray, depth_b: np.ndarray, T_b_from_a: np.ndarray, intrinsics,
                iterations: int = 12, max_depth_m: float = 4.0, stride: int = 2) -> np.ndarray:
    """``T_b_from_a`` improved by point-to-plane ICP with projective association.

    Pixels of a (every ``stride``-th row and column, depth below ``max_depth_m``) are matched
    to the pixel of b they land on; residuals are weighted by Tukey's biweight at 4.685 times
    their robust sigma (at least 5 mm).  For a good start (a few cm, a few degrees).
    """
    fx, fy, cx, cy = as_fxfycxcy(intrinsics)
    h, w = depth_b.shape
    pa = back_project(depth_a, intrinsics)[::stride, ::stride].reshape(-1, 3)
    pa = pa[(pa[:, 2] > 0) & (pa[:, 2] < max_depth_m)]
    pb = back_project(depth_b, intrinsics)
    nb = _normals(pb)
    T = np.asarray(T_b_from_a, dtype=np.float64).copy()
    for _ in range(iterations):
        q = pa @ T[:3, :3].T + T[:3, 3]
        u, v, zq, ok = _project(q, (fx, fy, cx, cy), w, h)
        uu, vv = np.where(ok, u, 0), np.where(ok, v, 0)
        tgt = pb[vv, uu]
        n = nb[vv, uu]
        ok &= (tgt[:, 2] > 0) & (np.abs(n).sum(axis=1) > 0)
        ok &= np.abs(tgt[:, 2] - q[:, 2]) < 0.1 + 0.03 * q[:, 2]
        if ok.sum() < 100:
            break
        q, tgt, n = q[ok], tgt[ok], n[ok]
        r = np.einsum("ij,ij->i", q - tgt, n)
        s = max(1.4826 * np.median(np.abs(r - np.median(r))), 0.005)
        c = 4.685 * s
        wgt = np.where(np.abs(r) < c, (1 - (r / c) ** 2) ** 2, 0.0)
        J = np.concatenate([np.cross(q, n), n], axis=1)
        A = (J * wgt[:, None]).T @ J
        b = -(J * wgt[:, None]).T @ r
        try:
            xi = np.linalg.solve(A + 1e-9 * np.eye(6), b)
        except np.linalg.LinAlgError:
            break
        T = _se3_exp(xi) @ T
        if np.linalg.norm(xi) < 1e-7:
            break
    return T


def zero_border(depth: np.ndarray, min_share: float = 0.02) -> tuple[int, int, int, int]:
    """Widths (left, right, top, bottom) in px of the zero frame round ``depth``: the outer
    columns / rows with fewer than ``min_share`` valid pixels (depth registered to a colour
    camera has one; a raw depth camera none)."""
    valid = depth > 0
    cols, rows = valid.mean(axis=0), valid.mean(axis=1)

    def run(share):
        n = 0
        while n < len(share) and share[n] < min_share:
            n += 1
        return n

    return run(cols), run(cols[::-1]), run(rows), run(rows[::-1])


def _footprint(shape, border, margin: int) -> np.ndarray:
    """(H, W) bool: inside ``border`` (left, right, top, bottom) shrunk by ``margin`` px."""
    h, w = shape
    left, right, top, bottom = border
    out = np.zeros(shape, dtype=bool)
    out[top + margin:h - bottom - margin, left + margin:w - right - margin] = True
    return out


def quantisation_step(depths_mm: np.ndarray, bins_m: np.ndarray = DEFAULT_BINS_M,
                      min_count: int = 3) -> np.ndarray:
    """Per depth bin, the median gap (m) between the distinct depth values of ``depths_mm``
    (uint16 mm, zeros ignored) that occur at least ``min_count`` times; NaN with fewer than 3
    such values in the bin."""
    values, counts = np.unique(np.asarray(depths_mm)[np.asarray(depths_mm) > 0],
                               return_counts=True)
    values = values[counts >= min_count].astype(np.float64) / 1000.0
    out = np.full(len(bins_m) - 1, np.nan)
    for i in range(len(bins_m) - 1):
        s = values[(values >= bins_m[i]) & (values < bins_m[i + 1])]
        if len(s) >= 3:
            out[i] = float(np.median(np.diff(s)))
    return out


def fit_quant_c(depths_mm: np.ndarray, min_count: int = 3, lo_m: float = 1.0,
                hi_m: float = 6.0) -> float:
    """The constant c of a disparity quantisation (step = c z^2, 1/m) fitted to the gaps between
    neighbouring distinct depth values of ``depths_mm`` (median of gap / z_mid^2 over the
    gaps between ``lo_m`` and ``hi_m``; gaps of missing levels are rejected as > 1.5x the
    running median)."""
    values, counts = np.unique(np.asarray(depths_mm)[np.asarray(depths_mm) > 0],
                               return_counts=True)
    z = values[counts >= min_count].astype(np.float64) / 1000.0
    gaps = np.diff(z)
    mid = (z[1:] + z[:-1]) / 2
    sel = (mid >= lo_m) & (mid <= hi_m)
    ratio = gaps[sel] / mid[sel] ** 2
    med = np.median(ratio)
    return float(np.median(ratio[ratio < 1.5 * med]))


@dataclasses.dataclass
class PairStats:
    """Frame-to-frame statistics per depth bin (arrays of ``len(bins_m) - 1``; NaN where a bin
    has fewer than ``min_pixels`` pixels).  Depths and differences in metres.

    ``n``: jointly valid landing pixels; ``sigma``: 1.4826 MAD of d; ``median``: median d;
    ``q99`` / ``q999``: 99 / 99.9 % quantiles of |d|; ``step``: quantisation step (median gap
    between distinct depth values); ``flicker``: share of landing pixels valid in one frame and
    not in the other (both directions, binned by the valid side's depth); ``n_flicker``: its
    denominator; ``jump``: share of jointly valid pixels with round(|d| / step) >= 1;
    ``jump2``: the same with >= 2 steps; ``lowfreq_sigma``: 1.4826 MAD of the box-mean of d
    over ``lowfreq_px`` (only pixels whose window is half valid); ``pairs``: pairs pooled;
    ``corr``: correlation of d between pixels ``corr_lags`` px apart (rows and columns, over
    :data:`CORR_RANGE_M`, |d| below the outlier cut).

    ``sigma`` is taken of d dithered by U(-step/2, step/2) with the dither's variance
    (step^2 / 12) taken off again (Sheppard): a plain MAD collapses to 0 when more than half
    of the differences are exactly 0, as they are between quantised frames of a still camera.
    """

    bins_m: np.ndarray
    n: np.ndarray
    sigma: np.ndarray
    median: np.ndarray
    q99: np.ndarray
    q999: np.ndarray
    step: np.ndarray
    flicker: np.ndarray
    n_flicker: np.ndarray
    jump: np.ndarray
    jump2: np.ndarray
    lowfreq_sigma: np.ndarray
    lowfreq_px: int
    pairs: int
    corr_lags: np.ndarray
    corr: np.ndarray

    def centres(self) -> np.ndarray:
        return (self.bins_m[1:] + self.bins_m[:-1]) / 2

    def to_json(self) -> dict:
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = [None if not np.isfinite(x) else round(float(x), 6) for x in v] \
                if isinstance(v, np.ndarray) else v
        return out


def _box_mean(values: np.ndarray, weights: np.ndarray, radius: int) -> tuple[np.ndarray,
                                                                             np.ndarray]:
    """Box means of ``values`` over (2 radius + 1)^2 windows counting only ``weights`` (0/1),
    and the share of the window that counts; via integral images."""
    def box(a):
        c = np.cumsum(np.cumsum(np.pad(a, ((1, 0), (1, 0))), axis=0), axis=1)
        h, w = a.shape
        r = radius
        y0 = np.clip(np.arange(h) - r, 0, h)
        y1 = np.clip(np.arange(h) + r + 1, 0, h)
        x0 = np.clip(np.arange(w) - r, 0, w)
        x1 = np.clip(np.arange(w) + r + 1, 0, w)
        return (c[y1][:, x1] - c[y0][:, x1] - c[y1][:, x0] + c[y0][:, x0])

    s = box(values * weights)
    n = box(weights.astype(np.float64))
    share = n / float((2 * radius + 1) ** 2)
    return np.where(n > 0, s / np.maximum(n, 1), 0.0), share


def _one_pair(depth_a, depth_b, T, intrinsics, bins, margin, lowfreq_px, outlier_m):
    """Per-pair pieces pooled by :func:`pair_stats`."""
    h, w = depth_b.shape
    border_b = tuple(max(x, y) for x, y in zip(zero_border(depth_a), zero_border(depth_b),
                                               strict=True))
    foot = _footprint((h, w), border_b, margin).ravel()
    out = {}
    # a -> b differences
    L = landing(depth_a, T, intrinsics, (h, w))
    inside = foot[L["dst"]] & foot[L["src"]]
    zb = depth_b.ravel()[L["dst"]].astype(np.float64) / 1000.0
    both = inside & (zb > 0)
    d = zb[both] - L["z_pred"][both]
    out["z"] = L["z_pred"][both]
    out["d"] = d
    # flicker a -> b: valid in a, landing on an invalid pixel of b
    out["fz"] = [L["z_pred"][inside]]
    out["flick"] = [zb[inside] == 0]
    # b -> a (the inverse transform): valid in b, invalid in a
    Tinv = np.linalg.inv(T)
    L2 = landing(depth_b, Tinv, intrinsics, depth_a.shape)
    inside2 = foot[L2["dst"]] & foot[L2["src"]]
    za = depth_a.ravel()[L2["dst"]]
    out["fz"].append(L2["z_pred"][inside2])
    out["flick"].append(za[inside2] == 0)
    # low-frequency part of d on b's grid (outliers beyond outlier_m left out)
    img = np.zeros(h * w)
    wgt = np.zeros(h * w)
    dst = L["dst"][both]
    keep = np.abs(d) < outlier_m
    img[dst[keep]] = d[keep]
    wgt[dst[keep]] = 1.0
    mean, share = _box_mean(img.reshape(h, w), wgt.reshape(h, w), lowfreq_px // 2)
    mean_at, share_at = mean.ravel()[dst], share.ravel()[dst]
    good = share_at >= 0.5
    out["lz"] = L["z_pred"][both][good]
    out["ld"] = mean_at[good]
    # spatial correlation of d at lags (pixels of CORR_RANGE_M, outliers out)
    zimg = np.zeros(h * w)
    zimg[dst] = L["z_pred"][both]
    use = (wgt > 0) & (zimg >= CORR_RANGE_M[0]) & (zimg < CORR_RANGE_M[1])
    x = np.where(use, img, np.nan).reshape(h, w)
    sums = np.zeros((len(CORR_LAGS), 6))
    for k, lag in enumerate(CORR_LAGS):
        for a, b in ((x[:, :-lag], x[:, lag:]), (x[:-lag], x[lag:])):
            ok = np.isfinite(a) & np.isfinite(b)
            a, b = a[ok], b[ok]
            sums[k] += (len(a), a.sum(), b.sum(), (a * a).sum(), (b * b).sum(), (a * b).sum())
    out["corr_sums"] = sums
    return out


def pair_stats(pairs: Iterable[tuple], bins_m: np.ndarray = DEFAULT_BINS_M, margin_px: int = 2,
               lowfreq_px: int = 31, min_pixels: int = 500, outlier_m: float = 0.15,
               steps: np.ndarray | None = None) -> PairStats:
    """Pool frame pairs ``(depth_a, depth_b, T_b_from_a or None, intrinsics)`` into
    :class:`PairStats`.

    ``margin_px``: landing pixels within this many px of either frame's zero border
    (:func:`zero_border`) are left out (a zero border is no flicker).  ``outlier_m``: |d| above
    this is left out of the low-frequency mean only.  ``steps``: the quantisation step per bin
    to use for the whole-step rates (default: measured on the frames' own distinct values).
    """
    bins = np.asarray(bins_m, dtype=np.float64)
    nb = len(bins) - 1
    zs, ds, fzs, fls, lzs, lds = [], [], [], [], [], []
    values = []
    count = 0
    corr_sums = np.zeros((len(CORR_LAGS), 6))
    for depth_a, depth_b, T, intrinsics in pairs:
        T = np.eye(4) if T is None else np.asarray(T, dtype=np.float64)
        part = _one_pair(depth_a, depth_b, T, intrinsics, bins, margin_px, lowfreq_px,
                         outlier_m)
        zs.append(part["z"])
        ds.append(part["d"])
        fzs += part["fz"]
        fls += part["flick"]
        lzs.append(part["lz"])
        lds.append(part["ld"])
        corr_sums += part["corr_sums"]
        values.append(depth_a[depth_a > 0])
        values.append(depth_b[depth_b > 0])
        count += 1
    z, d = np.concatenate(zs), np.concatenate(ds)
    fz, fl = np.concatenate(fzs), np.concatenate(fls)
    lz, ld = np.concatenate(lzs), np.concatenate(lds)
    step = quantisation_step(np.concatenate(values), bins) if steps is None else \
        np.asarray(steps, dtype=np.float64)
    nan = np.full(nb, np.nan)
    st = {k: nan.copy() for k in ("sigma", "median", "q99", "q999", "flicker", "jump", "jump2",
                                  "lowfreq_sigma")}
    n = np.zeros(nb, dtype=np.int64)
    nf = np.zeros(nb, dtype=np.int64)
    bi = np.digitize(z, bins) - 1
    fbi = np.digitize(fz, bins) - 1
    lbi = np.digitize(lz, bins) - 1
    dither = np.random.default_rng(0)
    for i in range(nb):
        di = d[bi == i]
        n[i] = len(di)
        fi = fl[fbi == i]
        nf[i] = len(fi)
        if len(fi) >= min_pixels:
            st["flicker"][i] = fi.mean()
        if len(di) < min_pixels:
            continue
        med = np.median(di)
        st["median"][i] = med
        q = step[i] if np.isfinite(step[i]) else 0.0
        dd = di + q * (dither.random(len(di)) - 0.5)
        mad = 1.4826 * np.median(np.abs(dd - np.median(dd)))
        st["sigma"][i] = math.sqrt(max(mad * mad - q * q / 12.0, 0.0))
        a = np.abs(di)
        st["q99"][i], st["q999"][i] = np.quantile(a, [0.99, 0.999])
        if np.isfinite(step[i]) and step[i] > 0:
            k = np.rint(a / step[i])
            st["jump"][i] = (k >= 1).mean()
            st["jump2"][i] = (k >= 2).mean()
        li = ld[lbi == i]
        if len(li) >= min_pixels:
            st["lowfreq_sigma"][i] = 1.4826 * np.median(np.abs(li - np.median(li)))
    cn, sa, sb, saa, sbb, sab = corr_sums.T
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = sab / cn - sa * sb / cn**2
        corr = cov / np.sqrt((saa / cn - (sa / cn) ** 2) * (sbb / cn - (sb / cn) ** 2))
    return PairStats(bins, n, st["sigma"], st["median"], st["q99"], st["q999"], step,
                     st["flicker"], nf, st["jump"], st["jump2"], st["lowfreq_sigma"],
                     lowfreq_px, count, np.asarray(CORR_LAGS), corr)


@dataclasses.dataclass
class EdgeStats:
    """Depth-edge behaviour of one or more images (rows and columns scanned).

    A pixel is *at an edge* when the depths ``span`` px before and after it (both valid) differ
    by more than ``rel_jump`` of the nearer and more than ``slope_ratio`` times the change over
    the next ``span`` px on either side (a step, not a slope); a run of such pixels along a
    scanline is one *crossing* (it covers the pixels within ~2 px of the step).  A pixel of a
    crossing is *flying* when its depth lies between the fore- and background by more than
    ``tol`` of the jump from both.

    ``crossings``; ``pixels``: pixels at an edge; ``flying_share``: flying / valid pixels at an
    edge; ``hole_share``: invalid / pixels at an edge; ``width_hist``: share of crossings with
    0, 1, 2, 3, >= 4 flying pixels; ``mean_width``: mean flying pixels per crossing that has
    one; ``flying_share_by_bin``: flying share per bin of the foreground depth (NaN below 200
    valid pixels).
    """

    crossings: int
    pixels: int
    flying_share: float
    hole_share: float
    width_hist: np.ndarray
    mean_width: float
    bins_m: np.ndarray
    flying_share_by_bin: np.ndarray

    def to_json(self) -> dict:
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, np.ndarray):
                v = [None if not np.isfinite(x) else round(float(x), 6) for x in v]
            elif isinstance(v, float):
                v = round(v, 6) if np.isfinite(v) else None
            out[f.name] = v
        return out


def _edge_scan(z: np.ndarray, span: int, rel_jump: float, slope_ratio: float, tol: float):
    """Rows of ``z`` (m, 0 = invalid): per crossing (flying, invalid, pixels, foreground z) and
    per edge pixel (valid, flying, foreground z)."""
    h, w = z.shape
    s = span
    pad = np.pad(z, ((0, 0), (2 * s, 2 * s)))
    a = pad[:, s:s + w]            # z[i - s]
    b = pad[:, 3 * s:3 * s + w]    # z[i + s]
    a2 = pad[:, 0:w]               # z[i - 2s]
    b2 = pad[:, 4 * s:4 * s + w]   # z[i + 2s]
    ok = (a > 0) & (b > 0) & (a2 > 0) & (b2 > 0)
    fore, back = np.minimum(a, b), np.maximum(a, b)
    jump = back - fore
    edge = ok & (jump > rel_jump * fore) & (jump > slope_ratio * np.abs(a - a2)) & \
        (jump > slope_ratio * np.abs(b - b2))
    valid = z > 0
    flying = edge & valid & (z > fore + tol * jump) & (z < back - tol * jump)
    # runs of edge pixels along each row
    flat = edge.ravel()
    start = flat.copy()
    start[1:] &= ~flat[:-1]
    start.reshape(h, w)[:, 0] = flat.reshape(h, w)[:, 0]
    run = np.cumsum(start) - 1
    idx = np.flatnonzero(flat)
    rid = run[idx]
    nrun = int(start.sum())
    n_fly = np.bincount(rid, weights=flying.ravel()[idx], minlength=nrun)
    n_bad = np.bincount(rid, weights=(~valid).ravel()[idx], minlength=nrun)
    n_pix = np.bincount(rid, minlength=nrun)
    return n_fly, n_bad, n_pix, edge & valid, flying, fore


def edge_stats(depths: Sequence[np.ndarray] | np.ndarray, bins_m: np.ndarray = DEFAULT_BINS_M,
               span: int = 3, rel_jump: float = 0.1, slope_ratio: float = 4.0,
               tol: float = 0.15) -> EdgeStats:
    """:class:`EdgeStats` of one (H, W) uint16 mm image or a list of them (pooled)."""
    if isinstance(depths, np.ndarray) and depths.ndim == 2:
        depths = [depths]
    fly, bad, pix = [], [], []
    ev_z, ev_f = [], []
    for depth in depths:
        z = depth.astype(np.float64) / 1000.0
        for img in (z, z.T):
            n_fly, n_bad, n_pix, ev, fl, fore = _edge_scan(img, span, rel_jump, slope_ratio,
                                                          tol)
            fly.append(n_fly)
            bad.append(n_bad)
            pix.append(n_pix)
            ev_z.append(fore[ev])
            ev_f.append(fl[ev])
    n_fly, n_bad, n_pix = np.concatenate(fly), np.concatenate(bad), np.concatenate(pix)
    ez, ef = np.concatenate(ev_z), np.concatenate(ev_f)
    crossings = len(n_pix)
    pixels = int(n_pix.sum())
    n_valid = pixels - n_bad.sum()
    hist = np.bincount(np.minimum(n_fly.astype(np.int64), 4), minlength=5)[:5].astype(float)
    hist = hist / max(crossings, 1)
    with_fly = n_fly[n_fly > 0]
    bins = np.asarray(bins_m, dtype=np.float64)
    by_bin = np.full(len(bins) - 1, np.nan)
    bi = np.digitize(ez, bins) - 1
    for i in range(len(bins) - 1):
        sel = bi == i
        if sel.sum() >= 200:
            by_bin[i] = ef[sel].mean()
    return EdgeStats(
        crossings=crossings, pixels=pixels,
        flying_share=float(n_fly.sum() / n_valid) if n_valid else float("nan"),
        hole_share=float(n_bad.sum() / pixels) if pixels else float("nan"),
        width_hist=hist,
        mean_width=float(with_fly.mean()) if len(with_fly) else 0.0,
        bins_m=bins, flying_share_by_bin=by_bin)


# ----------------------------------------------------------------------------- harsh pairs

#: The stored scenes' room layouts :func:`harsh_pair` renders (sim_fixtures.scenes).
HARSH_LAYOUTS = ("office", "lounge", "lab", "storage", "meeting")


@dataclasses.dataclass(frozen=True, eq=False)
class HarshPair:
    """A NO-CHANGE pair of one room layout with the harsh Kinect model.

    ``reference`` / ``current``: lists of (H, W) uint16 mm frames (0 = none), each epoch with
    its own error field and independent per-frame noise; ``intrinsics``: the nominal
    ``hw.depth.Intrinsics`` (the model's true ones differ, as a real camera's do);
    ``T_ref_from_cur``: (4, 4) the true transform from the current camera frame to the
    reference one (the identity when the camera did not move); ``noise``: the model used.
    """

    layout: str
    seed: int
    offset_m: float
    rotation_deg: float
    reference: list
    current: list
    intrinsics: object
    T_ref_from_cur: np.ndarray
    noise: object


def _layout(name: str):
    from sim_fixtures import scenes

    makers = {"office": scenes._office, "lounge": scenes._lounge, "lab": scenes._lab,
              "storage": scenes._storage, "meeting": scenes._meeting}
    if name not in makers:
        raise ValueError(f"layout {name!r}: expected one of {', '.join(HARSH_LAYOUTS)}")
    return makers[name]()


def harsh_pair(layout: str = "office", seed: int = 0, offset_m: float = 0.0,
               rotation_deg: float | None = None, frames: tuple[int, int] = (3, 3),
               noise=None) -> HarshPair:
    """Render ``layout`` (a stored scene's room, unchanged) twice with the harsh Kinect model
    (``harsh_noise.RealisticKinectNoise()`` unless ``noise`` is given): the reference from the
    scene's camera pose, the current from the same pose moved ``offset_m`` in a random
    direction and turned ``rotation_deg`` (default 40 deg per metre of offset: 0.8 deg at
    2 cm) about a random axis (``scenes.pose_offset``, drawn from ``seed``).  Deterministic in
    its arguments; nothing is stored.  About 1 s on one core.

    Reference frame k draws its noise from ``default_rng([seed, 0, k])`` with the error field
    of epoch ``2 seed``, current frame k from ``default_rng([seed, 1, k])`` with the field of
    epoch ``2 seed + 1``: independent noise and independent fields even at offset 0.
    """
    from sim_fixtures.harsh_noise import RealisticKinectNoise
    from sim_fixtures.render import render
    from sim_fixtures.scenes import pose_offset

    noise = RealisticKinectNoise() if noise is None else noise
    objs, pose = _layout(layout)
    rotation = 40.0 * offset_m if rotation_deg is None else float(rotation_deg)
    cur_pose = pose if offset_m == 0 and rotation == 0 else pose_offset(
        pose, offset_m, rotation, 7919 * int(seed) + HARSH_LAYOUTS.index(layout))
    baseline = getattr(noise, "projector_baseline_m", None)
    r_ref = render(objs, pose, None, None, baseline)
    r_cur = r_ref if cur_pose is pose else render(objs, cur_pose, None, None, baseline)
    epochs = [noise, noise]
    if hasattr(noise, "for_epoch"):
        epochs = [noise.for_epoch(2 * int(seed)), noise.for_epoch(2 * int(seed) + 1)]
    ref = [epochs[0].apply(r_ref, np.random.default_rng([seed, 0, k])) for k in range(frames[0])]
    cur = [epochs[1].apply(r_cur, np.random.default_rng([seed, 1, k])) for k in range(frames[1])]
    T = np.eye(4) if cur_pose is pose else np.linalg.inv(pose.matrix()) @ cur_pose.matrix()
    return HarshPair(layout, int(seed), float(offset_m), rotation, ref, cur, r_ref.intrinsics,
                     T, noise)


def harsh_pairs(seed: int = 0, offset_m: float = 0.0, layouts: Sequence[str] = HARSH_LAYOUTS,
                **kw):
    """:func:`harsh_pair` of every layout in ``layouts`` (a generator, one at a time)."""
    for name in layouts:
        yield harsh_pair(name, seed, offset_m, **kw)
