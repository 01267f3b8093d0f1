"""Depth noise models: a Kinect v1 (structured light) model and the paper's plain Gaussian.

Both turn a :class:`~sim_fixtures.render.Render` into a (H, W) uint16 depth image in
millimetres (0 = no reading), deterministically given a ``numpy.random.Generator``; call once per
frame with a fresh generator for independent frames.

Kinect model (:class:`KinectNoise`), where the constants come from:

- Axial noise, Nguyen, Izadi & Lovell, "Modeling Kinect Sensor Noise for Improved 3D
  Reconstruction and Tracking", 3DIMPVT 2012, eq. (4)-(5):
  ``sigma_z(z, theta) = 0.0012 + 0.0019 (z - 0.4)^2`` m for incidence theta below 60 degrees,
  plus ``0.0001 / sqrt(z) * theta^2 / (pi/2 - theta)^2`` above.  Their sigma was measured on the
  sensor's (quantised) output, so we draw Gaussian noise with
  ``sqrt(sigma_z^2 - q^2 / 12)`` before quantising: the output's std is then sigma_z.
- Quantisation, Khoshelham & Oude Elberink, "Accuracy and Resolution of Kinect Depth Data for
  Indoor Mapping Applications", Sensors 12(2), 2012: depth comes from an integer disparity, so
  levels are equally spaced in 1/z and the step grows as ``q(z) = c z^2``; their resolution
  reaches ~7 cm at 5 m, i.e. c ~ 0.0028 /m.  We use c = 0.00285 /m: levels at
  ``z_k = 1 / (c k)`` for integer k (2.85 mm at 1 m, 11.4 mm at 2 m, 45.6 mm at 4 m).
- Range, K&OE 2012: 0.5-5 m; readings (after noise) outside are dropped (0).
- Grazing incidence: Nguyen et al. found the noise exploding toward 90 degrees; the sensor returns
  nothing there.  We drop a pixel with probability rising linearly from 0 at 78 degrees to 1 at
  88 degrees (our choice, not a published constant).
- Depth discontinuities: the correlation window straddles the edge and the match fails; pixels
  within ``edge_band_px`` of a jump larger than ``edge_rel_jump * z`` are dropped with
  probability ``edge_drop_prob`` (our choice).
- Projector shadows: the IR projector sits 7.5 cm from the IR camera (K&OE 2012: baseline
  ~7.5 cm).  Seen from the device, the projector is on the camera's right (+x), so shadows
  fall on the image-left of foreground objects; surface points the projector cannot light give
  no reading (``Render.shadow``, computed by ray casting from the projector).
- Lateral noise (optional, off by default): Nguyen et al. measured ~0.8 px; with
  ``lateral_sigma_px > 0`` each pixel reads the ideal depth of a randomly offset neighbour.

Paper protocol (:class:`GaussianNoise`): Table 1 of the paper, z + N(0, sigma^2) with sigma =
0.001, 0.01 or 0.1 m; no quantisation (beyond the millimetre of the uint16 format), no range
limit, no dropouts, no shadows.

The harsher models, :class:`~sim_fixtures.harsh_noise.RealisticKinectNoise` (the Kinect
model fitted to real Xtion depth) and :class:`~sim_fixtures.harsh_noise.StereoNoise` (RealSense
D4xx-like), live in :mod:`sim_fixtures.harsh_noise`, which uses this module's helpers;
:func:`noise_from_json` reads all four.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from sim_fixtures.render import Render

__all__ = [
    "KinectNoise",
    "GaussianNoise",
    "PAPER_SIGMAS_M",
    "kinect_axial_sigma",
    "quantise_depth",
    "noise_from_json",
    "to_millimetres",
]

#: The paper's Table 1: the three depth noise levels of its simulated room, metres.
PAPER_SIGMAS_M = (0.001, 0.01, 0.1)


def kinect_axial_sigma(z: np.ndarray, theta: np.ndarray | float = 0.0) -> np.ndarray:
    """Nguyen et al. 2012 axial std (metres) at depth ``z`` (m) and incidence ``theta`` (rad)."""
    z = np.asarray(z, dtype=np.float64)
    theta = np.asarray(theta, dtype=np.float64)
    sigma = 0.0012 + 0.0019 * (z - 0.4) ** 2
    steep = theta > math.radians(60)
    with np.errstate(divide="ignore", invalid="ignore"):
        extra = 0.0001 / np.sqrt(np.maximum(z, 1e-6)) * theta**2 / np.maximum(
            math.pi / 2 - theta, 1e-3) ** 2
    return np.where(steep, sigma + extra, sigma)


def quantise_depth(z: np.ndarray, c: float) -> np.ndarray:
    """Snap depths ``z`` (m, > 0) to disparity-like levels ``1 / (c k)``, k integer >= 1.

    The spacing between neighbouring levels near z is about ``c z^2``.
    """
    z = np.asarray(z, dtype=np.float64)
    with np.errstate(divide="ignore"):
        k = np.maximum(np.rint(1.0 / (c * z)), 1.0)
    return 1.0 / (c * k)


def to_millimetres(z: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(H, W) metres + validity -> (H, W) uint16 mm, 0 where invalid or out of 1..65535 mm."""
    mm = np.rint(np.where(valid, z, 0.0) * 1000.0)
    ok = valid & (mm >= 1) & (mm <= 65535)
    return np.where(ok, mm, 0).astype(np.uint16)


@dataclasses.dataclass(frozen=True)
class KinectNoise:
    """Kinect v1-like depth: axial noise, quantisation, range, grazing, edges, shadows.

    Distances in metres, angles in degrees; see the module docstring for the sources.
    """

    near_m: float = 0.5
    far_m: float = 5.0
    quant_c_per_m: float = 0.00285
    grazing_start_deg: float = 78.0
    grazing_stop_deg: float = 88.0
    edge_rel_jump: float = 0.05
    edge_band_px: int = 1
    edge_drop_prob: float = 0.5
    projector_baseline_m: float = 0.075
    lateral_sigma_px: float = 0.0

    kind = "kinect"

    def sigma(self, z: np.ndarray, theta: np.ndarray | float = 0.0) -> np.ndarray:
        """Target std of the output (m) at depth ``z`` (m), incidence ``theta`` (rad)."""
        return kinect_axial_sigma(z, theta)

    def step(self, z: np.ndarray) -> np.ndarray:
        """Approximate quantisation step (m) at depth ``z`` (m): ``c z^2``."""
        return self.quant_c_per_m * np.asarray(z, dtype=np.float64) ** 2

    def apply(self, r: Render, rng: np.random.Generator) -> np.ndarray:
        """One noisy frame of ``r``: (H, W) uint16 mm, 0 = no reading.

        ``r`` must have been rendered with ``projector_baseline_m`` equal to this model's
        (``render(..., projector_baseline_m=noise.projector_baseline_m)``) for shadows to show.
        """
        z = r.depth
        theta = np.arccos(np.clip(r.cos_incidence, 0.0, 1.0))
        shadow = r.shadow
        if self.lateral_sigma_px > 0:
            z, theta, shadow = _lateral_shift(rng, self.lateral_sigma_px, z, theta, shadow)
        hit = z > 0
        edges = _edge_band(z, self.edge_rel_jump, self.edge_band_px)
        # draws happen in a fixed order, always for every pixel (reproducible)
        gauss = rng.standard_normal(z.shape)
        u_graze = rng.random(z.shape)
        u_edge = rng.random(z.shape)
        sig = self.sigma(z, theta)
        q = self.step(z)
        sig_pre = np.sqrt(np.maximum(sig**2 - q**2 / 12.0, 0.0))
        noisy = np.where(hit, z + sig_pre * gauss, 1.0)
        noisy = quantise_depth(np.maximum(noisy, 1e-3), self.quant_c_per_m)
        t_deg = np.degrees(theta)
        p_graze = np.clip(
            (t_deg - self.grazing_start_deg) / (self.grazing_stop_deg - self.grazing_start_deg),
            0.0, 1.0,
        )
        valid = (
            hit
            & ~shadow
            & (noisy >= self.near_m)
            & (noisy <= self.far_m)
            & (u_graze >= p_graze)
            & ~(edges & (u_edge < self.edge_drop_prob))
        )
        return to_millimetres(noisy, valid)

    def to_json(self) -> dict:
        out = {"model": self.kind}
        out.update(dataclasses.asdict(self))
        out["axial_sigma"] = "0.0012 + 0.0019 (z - 0.4)^2 m (+ angle term above 60 deg), " \
            "Nguyen et al. 2012"
        out["quantisation"] = "levels 1/(c k), step ~ c z^2, Khoshelham & Oude Elberink 2012"
        return out


@dataclasses.dataclass(frozen=True)
class GaussianNoise:
    """The paper's protocol (Table 1): ideal depth + N(0, sigma_m^2), nothing else."""

    sigma_m: float

    kind = "gaussian"

    def apply(self, r: Render, rng: np.random.Generator) -> np.ndarray:
        """One noisy frame: (H, W) uint16 mm, 0 only where nothing is hit (or z + noise <= 0)."""
        gauss = rng.standard_normal(r.depth.shape)
        hit = r.depth > 0
        return to_millimetres(r.depth + self.sigma_m * gauss, hit)

    def to_json(self) -> dict:
        return {"model": self.kind, "sigma_m": self.sigma_m,
                "source": "paper Table 1: normal distribution, mu = 0"}


def noise_from_json(data: dict):
    """Inverse of ``to_json`` (unknown keys such as descriptions are ignored): a
    KinectNoise, GaussianNoise, or one of sim_fixtures.harsh_noise's RealisticKinectNoise and
    StereoNoise."""
    if data["model"] == "gaussian":
        return GaussianNoise(float(data["sigma_m"]))
    if data["model"] == "kinect":
        names = {f.name for f in dataclasses.fields(KinectNoise)}
        return KinectNoise(**{k: v for k, v in data.items() if k in names})
    # imported here: harsh_noise builds on this module's helpers
    from sim_fixtures.harsh_noise import RealisticKinectNoise, StereoNoise

    for cls in (RealisticKinectNoise, StereoNoise):
        if data["model"] == cls.kind:
            names = {f.name for f in dataclasses.fields(cls)}
            kw = {k: v for k, v in data.items() if k in names}
            if "border_px" in kw:
                kw["border_px"] = tuple(int(v) for v in kw["border_px"])
            return cls(**kw)
    raise ValueError(f"unknown noise model {data['model']!r}; known: 'kinect', 'gaussian', "
                     f"'{RealisticKinectNoise.kind}', '{StereoNoise.kind}'")


def _edge_band(z: np.ndarray, rel: float, band: int) -> np.ndarray:
    """(H, W) bool: pixels within ``band`` px of a depth jump > ``rel * z`` or of a no-hit."""
    jump = np.zeros(z.shape, dtype=bool)
    for axis in (0, 1):
        a = np.take(z, range(0, z.shape[axis] - 1), axis=axis)
        b = np.take(z, range(1, z.shape[axis]), axis=axis)
        j = (np.abs(a - b) > rel * np.minimum(a, b)) | ((a > 0) != (b > 0))
        pad_lo = [(0, 0), (0, 0)]
        pad_hi = [(0, 0), (0, 0)]
        pad_lo[axis] = (1, 0)
        pad_hi[axis] = (0, 1)
        jump |= np.pad(j, pad_hi) | np.pad(j, pad_lo)
    out = jump.copy()
    for _ in range(max(band, 1) - 1):
        grown = out.copy()
        grown[1:] |= out[:-1]
        grown[:-1] |= out[1:]
        grown[:, 1:] |= out[:, :-1]
        grown[:, :-1] |= out[:, 1:]
        out = grown
    return out


def _lateral_shift(rng, sigma_px, *images):
    """Each pixel reads its inputs from a neighbour offset by round(N(0, sigma_px)) px."""
    h, w = images[0].shape
    dv = np.rint(rng.normal(0.0, sigma_px, (h, w))).astype(np.int64)
    du = np.rint(rng.normal(0.0, sigma_px, (h, w))).astype(np.int64)
    vv = np.clip(np.arange(h)[:, None] + dv, 0, h - 1)
    uu = np.clip(np.arange(w)[None, :] + du, 0, w - 1)
    return tuple(img[vv, uu] for img in images)
