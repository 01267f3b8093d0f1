"""A depth camera's noise, as every decision of a check needs it: :class:`NoiseProfile`.

The axial noise of one reading at depth z (metres) is

    sigma(z) = sqrt(axial(z)^2 + step(z)^2 / 12),   axial(z) = a0 + a1 z + a2 z^2,
                                                    step(z) = c z^2

(``axial_m`` = (a0, a1, a2); ``step_per_m`` = c, the disparity quantisation of a
structured-light or stereo camera, 0 for a time-of-flight one, whose 1 mm steps are lost in its
noise).  A profile also carries the camera's range, the baseline that casts shadows (projector or
second imager) and, when it was measured, the flicker and edge figures and the measured sigma per
depth bin it was fitted to.

Built-in profiles (:data:`BUILTIN`) are made from published figures (each says which); a profile
measured by ``robot-change calibrate`` is saved as JSON (:meth:`NoiseProfile.save`) and wins over
the configured built-in.  Every reference capture measures its frames too
(:mod:`robot_change.noise.estimate`) and raises the profile where its noise is larger
(:meth:`NoiseProfile.raised_by`): the profile in use is kept with the station's reference.

Kernels get a profile as one float64 array (:meth:`NoiseProfile.kernel_table`): sigma tabulated
every :data:`TABLE_STEP_M` metres, read by :func:`robot_change.noise.kernels.sigma_at`.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from hw.atomic import write_atomically
from hw.realsense_record import UNNAMED_CAMERA
from robot_change import validate
from robot_change.errors import BadValue, InputError

log = logging.getLogger(__name__)

__all__ = [
    "BUILTIN",
    "AUTO_PROFILE",
    "DEFAULT_PROFILE",
    "DEFAULT_NEAR_M",
    "NoiseProfile",
    "PRINCIPLES",
    "RAISE_TOLERANCE",
    "ProfileFileError",
    "TABLE_STEP_M",
    "TABLE_END_M",
    "builtin_profile",
    "profile_for_camera",
    "resolve_profile",
    "sigma_table",
]

#: How a camera measures depth.
PRINCIPLES = ("structured_light", "stereo", "time_of_flight", "simulated")
#: Spacing and end of the sigma table handed to kernels (metres); beyond the end sigma grows
#: with z^2 from the last entry.
TABLE_STEP_M = 0.05
TABLE_END_M = 12.0
#: A reference capture's frames raise its profile only where they are noisier than this many
#: times its sigma (a few frames' estimate scatters by ~10 %).
RAISE_TOLERANCE = 1.25
FILE_FORMAT = "robot_change.noise_profile"
FILE_VERSION = 1

_num = functools.partial(validate.number, "NoiseProfile")
_int = functools.partial(validate.whole, "NoiseProfile")


class ProfileFileError(InputError):
    """A camera profile file that cannot be read: missing, not JSON, another format, a newer
    version, or a value out of range (the message names the file and the field)."""


@dataclasses.dataclass(frozen=True)
class NoiseProfile:
    """One depth camera's noise model (module docstring).  Distances in metres."""

    name: str
    principle: str
    axial_m: tuple[float, float, float]
    step_per_m: float
    # The range the camera reads reliably: nothing nearer is read; what lies farther is never
    # evidence of a change (its steps and its errors there are not noise-like: an Xtion's
    # study room at 4.8 m, docs/evaluation.md).
    min_range_m: float
    max_range_m: float
    # Offset of what casts the camera's shadows (a structured-light projector, a stereo
    # camera's second imager) from the depth camera: holes beside near surfaces this wide,
    # b f (1/z_near - 1/z) pixels.  0: none (time of flight).
    shadow_baseline_m: float
    # Width of the band at depth edges where readings lie between the two surfaces (flying
    # pixels), pixels.
    edge_px: int = 2
    # Measured (0 when not): the share of pixels that change between a reading and none from
    # one frame to the next, and the share of valid pixels that jump by a quantisation step.
    flicker_valid: float = 0.0
    flicker_step: float = 0.0
    # Where the figures come from: a publication for a built-in, the source and date of a
    # measurement.
    source: str = ""
    # A measured sigma per depth bin, ((bin centre m, sigma m, pixels), ...), and how it is
    # used: "" (not: the polynomial alone), "raise" (sigma is the larger of the two:
    # a reference capture's frames), "replace" (the measurement alone, the polynomial's
    # shape carrying it beyond the measured depths: robot-change calibrate).
    measured: tuple[tuple[float, float, int], ...] = ()
    measured_use: str = ""

    @property
    def near_m(self) -> float:
        """The nearest depth the module uses from this camera unless told (metres):
        :data:`DEFAULT_NEAR_M`, or ``min_range_m`` where the camera reads reliably nearer (a
        RealSense D415 / D435 from 0.3 m, the D405 from 7 cm)."""
        return min(DEFAULT_NEAR_M, self.min_range_m)

    def __post_init__(self) -> None:
        validate.text("NoiseProfile", "name", self.name, max_bytes=64)
        validate.choice("NoiseProfile", "principle", self.principle, PRINCIPLES)
        if not (isinstance(self.axial_m, tuple) and len(self.axial_m) == 3):
            raise BadValue("NoiseProfile", "axial_m", self.axial_m,
                           "three numbers (a0, a1, a2): axial sigma a0 + a1 z + a2 z^2, metres")
        for a in self.axial_m:
            _num("axial_m", a, -1.0, 1.0)
        _num("step_per_m", self.step_per_m, 0.0, 1.0, unit=" per metre")
        _num("min_range_m", self.min_range_m, 0.0, 10.0, unit=" metres")
        _num("max_range_m", self.max_range_m, self.min_range_m, 100.0, low_open=True,
             unit=" metres")
        _num("shadow_baseline_m", self.shadow_baseline_m, 0.0, 1.0, unit=" metres")
        _int("edge_px", self.edge_px, 0, 16, unit=" pixels")
        _num("flicker_valid", self.flicker_valid, 0.0, 1.0)
        _num("flicker_step", self.flicker_step, 0.0, 1.0)
        validate.text("NoiseProfile", "source", self.source, max_bytes=1000)
        validate.choice("NoiseProfile", "measured_use", self.measured_use,
                        ("", "raise", "replace"))
        if self.measured_use and not self.measured:
            raise BadValue("NoiseProfile", "measured", self.measured,
                           f"at least one bin when measured_use is {self.measured_use!r}")
        for zb, sb, _nb in self.measured:
            _num("measured depth", zb, 0.0, 100.0, low_open=True, unit=" metres")
            _num("measured sigma", sb, 0.0, 10.0, low_open=True, unit=" metres")
        z = np.linspace(0.1, TABLE_END_M, 240)
        if not np.all(self._axial(z) > 0.0):
            raise BadValue("NoiseProfile", "axial_m", self.axial_m,
                           f"positive at every depth from 0.1 to {TABLE_END_M:g} m")

    def _axial(self, z: np.ndarray) -> np.ndarray:
        a0, a1, a2 = self.axial_m
        return a0 + a1 * z + a2 * z * z

    def _polynomial(self, z: np.ndarray) -> np.ndarray:
        step = self.step_per_m * z * z
        return np.sqrt(self._axial(z) ** 2 + step * step / 12.0)

    def sigma(self, z) -> np.ndarray:
        """Axial noise of one reading at depth ``z`` (m, any shape), metres: the polynomial,
        the measurement, or the larger of the two (``measured_use``)."""
        z = np.asarray(z, dtype=np.float64)
        own = self._polynomial(z)
        if not self.measured_use:
            return own
        env = self._envelope(z)
        return env if self.measured_use == "replace" else np.maximum(own, env)

    def margin(self, z, sigmas: float, pose_m: float) -> np.ndarray:
        """How much two readings of this camera at depth ``z`` (m) may differ and still be
        one surface: ``sigmas`` sigmas of their difference and of ``pose_m`` (what a
        registration leaves), k sqrt(2 sigma(z)^2 + pose^2), metres (the NumPy face of
        :func:`robot_change.noise.kernels.margin_at`)."""
        s = self.sigma(z)
        return sigmas * np.sqrt(2.0 * s * s + pose_m * pose_m)

    def step(self, z) -> np.ndarray:
        """Quantisation step at depth ``z`` (m), metres (at least the 1 mm of a depth image)."""
        return np.maximum(self.step_per_m * np.asarray(z, dtype=np.float64) ** 2, 0.001)

    def kernel_table(self) -> np.ndarray:
        """(n,) float64: sigma(z) at z = 0, TABLE_STEP_M, ..., TABLE_END_M, for
        :func:`robot_change.noise.kernels.sigma_at`."""
        z = np.arange(0.0, TABLE_END_M + TABLE_STEP_M / 2, TABLE_STEP_M)
        return np.ascontiguousarray(self.sigma(np.maximum(z, 1e-3)), dtype=np.float64)

    def _envelope(self, z: np.ndarray) -> np.ndarray:
        """sigma (m) at ``z`` (m) as the measured bins say: interpolated between them, and
        beyond them the polynomial's sigma scaled to meet the nearest bin."""
        zb = np.array([m[0] for m in self.measured], dtype=np.float64)
        sb = np.array([m[1] for m in self.measured], dtype=np.float64)
        order = np.argsort(zb)
        zb, sb = zb[order], sb[order]
        flat = np.atleast_1d(z).astype(np.float64)
        out = np.interp(flat, zb, sb)
        below, above = flat < zb[0], flat > zb[-1]
        out[below] = self._polynomial(flat[below]) * (sb[0] / self._polynomial(zb[0]))
        out[above] = self._polynomial(flat[above]) * (sb[-1] / self._polynomial(zb[-1]))
        return out.reshape(np.shape(z))

    def raised_by(self, bins, source: str, *, tolerance: float = 1.0, flicker_valid: float = 0.0,
                  flicker_step: float = 0.0) -> NoiseProfile:
        """This profile where measured ``bins`` ((bin centre m, sigma m, pixels), ...) are
        more than ``tolerance`` times its sigma: sigma is then the larger of the two (bins
        within the tolerance count as agreeing).  A still camera's frames show only the
        noise from frame to frame, not what a revisit adds (its pose, the error that stays
        with a view): a measurement at capture raises a profile and never lowers it."""
        said = [(float(z), float(sb) if sb > tolerance * float(self.sigma(z)) else
                 float(self.sigma(z)), int(n)) for z, sb, n in bins]
        noted = dataclasses.replace(self, flicker_valid=flicker_valid, flicker_step=flicker_step)
        if all(sb <= float(self.sigma(z)) for z, sb, _ in said):
            return dataclasses.replace(noted, source=f"{self.source}; {source}: not noisier")
        if self.measured_use == "raise":  # raised before: both measurements, the larger
            mine = dict((z, (sb, n)) for z, sb, n in self.measured)
            said = [(z, max(sb, mine.get(z, (0.0, 0))[0]), n) for z, sb, n in said]
        return dataclasses.replace(
            noted, name=self.name if self.name.endswith("+measured") else f"{self.name}+measured",
            measured=tuple(said), measured_use=self.measured_use or "raise",
            source=f"{self.source}; raised by {source}")

    def replaced_by(self, bins, source: str, *, flicker_valid: float, flicker_step: float,
                    step_per_m: float, edge_px: int) -> NoiseProfile:
        """A measured profile (``robot-change calibrate``): sigma is the measured ``bins``
        ((bin centre m, sigma m, pixels), ...), this profile's shape beyond them; the measured
        step, flicker and edge figures; this profile's principle and range."""
        return dataclasses.replace(
            self, name=f"measured:{self.name}", step_per_m=step_per_m, edge_px=edge_px,
            flicker_valid=flicker_valid, flicker_step=flicker_step,
            measured=tuple((float(z), float(sb), int(n)) for z, sb, n in bins),
            measured_use="replace", source=source)

    def summary(self) -> dict[str, Any]:
        """A short JSON-ready description: name, principle, sigma at 1 / 2 / 3 / 4 m (mm),
        the step at 2 m (mm), range, source."""
        return {"name": self.name, "principle": self.principle,
                "sigma_mm": {f"{z:g}m": round(float(self.sigma(z)) * 1000, 1)
                             for z in (1.0, 2.0, 3.0, 4.0)},
                "step_at_2m_mm": round(float(self.step(2.0)) * 1000, 1),
                "range_m": [self.min_range_m, self.max_range_m], "source": self.source}

    def to_dict(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out["axial_m"] = list(self.axial_m)
        out["measured"] = [list(m) for m in self.measured]
        return out

    @classmethod
    def from_dict(cls, d: Any, where: str = "profile") -> NoiseProfile:
        """A profile from :meth:`to_dict`'s output; :class:`BadValue` naming the field for a
        wrong or missing one."""
        if not isinstance(d, dict):
            raise BadValue("NoiseProfile", where, d, "a JSON object")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise BadValue("NoiseProfile", unknown[0], d[unknown[0]],
                           f"one of the known fields ({', '.join(sorted(names))})")
        missing = [f.name for f in dataclasses.fields(cls)
                   if f.name not in d and f.default is dataclasses.MISSING]
        if missing:
            raise BadValue("NoiseProfile", missing[0], None, "given (a required field)")
        kw = dict(d)
        axial = kw["axial_m"]
        kw["axial_m"] = tuple(axial) if isinstance(axial, list) else axial
        measured = kw.get("measured", ())
        if not isinstance(measured, (list, tuple)) or not all(
                isinstance(m, (list, tuple)) and len(m) == 3 for m in measured):
            raise BadValue("NoiseProfile", "measured", measured,
                           "a list of [depth m, sigma m, pixels]")
        kw["measured"] = tuple((float(m[0]), float(m[1]), int(m[2])) for m in measured)
        return cls(**kw)

    def save(self, path) -> Path:
        """Write the profile as JSON (atomically)."""
        path = Path(path)
        text = json.dumps({"format": FILE_FORMAT, "version": FILE_VERSION,
                           "profile": self.to_dict()}, indent=2)
        write_atomically(path, (text + "\n").encode())
        return path

    @classmethod
    def load(cls, path) -> NoiseProfile:
        """A profile file written by :meth:`save`; :class:`ProfileFileError` naming the file
        and what is wrong."""
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except OSError as exc:
            raise ProfileFileError(f"camera profile {path}: cannot be read ({exc.strerror or exc})"
                                   ) from exc
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ProfileFileError(f"camera profile {path}: not JSON ({exc}); write one with "
                                   "`robot-change calibrate --source URI --out FILE`") from exc
        kind = data.get("format") if isinstance(data, dict) else None
        if kind != FILE_FORMAT:
            raise ProfileFileError(f"camera profile {path}: not a robot_change camera profile "
                                   f"(format {kind!r}, expected {FILE_FORMAT!r})")
        if data.get("version") != FILE_VERSION:
            raise ProfileFileError(f"camera profile {path}: version {data.get('version')!r}, this "
                                   f"robot_change reads version {FILE_VERSION}")
        try:
            return cls.from_dict(data.get("profile"))
        except BadValue as exc:
            raise ProfileFileError(f"camera profile {path}: {exc}") from exc


def _structured_light(name: str, min_range_m: float, max_range_m: float, source: str
                      ) -> NoiseProfile:
    """A PrimeSense-design camera: the Kinect's axial noise (Nguyen, Izadi & Lovell 2012:
    0.0012 + 0.0019 (z - 0.4)^2 m), disparity steps 2.85e-3 z^2 (Khoshelham & Oude Elberink
    2012; 1/8 px over the 7.5 cm projector baseline at f ~ 580 px) and projector shadows."""
    a2 = 0.0019
    return NoiseProfile(
        name=name, principle="structured_light",
        axial_m=(0.0012 + a2 * 0.16, -2 * 0.4 * a2, a2),
        step_per_m=2.85e-3, min_range_m=min_range_m,
        max_range_m=max_range_m, shadow_baseline_m=0.075, edge_px=2, source=source)


def _stereo(name: str, baseline_m: float, hfov_deg: float, width_px: int, min_range_m: float,
            max_range_m: float, source: str) -> NoiseProfile:
    """An active stereo camera at its default width: depth RMS error z^2 s / (f b) with the
    subpixel figure s = 0.08 px (Intel's depth RMS formula, Grunnet-Jepsen et al., "Tuning
    depth cameras for best performance", Intel 2019), disparity in 1/32 px (step z^2 /
    (32 f b)), f from the horizontal field of view."""
    f = 0.5 * width_px / math.tan(math.radians(hfov_deg) / 2)
    return NoiseProfile(
        name=name, principle="stereo", axial_m=(0.0005, 0.0, 0.08 / (f * baseline_m)),
        step_per_m=1.0 / (32.0 * f * baseline_m), min_range_m=min_range_m,
        max_range_m=max_range_m, shadow_baseline_m=baseline_m, edge_px=2, source=source)


#: The built-in profiles, by name (``[camera] profile`` in the configuration).
BUILTIN: dict[str, NoiseProfile] = {
    p.name: p for p in (
        _structured_light(
            "kinect_v1", 0.5, 4.5,
            "built-in: Microsoft Kinect v1; axial noise Nguyen, Izadi & Lovell, 3DIMPVT 2012; "
            "disparity steps Khoshelham & Oude Elberink, Sensors 12(2) 2012; reads 0.5-5 m, "
            "evidence to 4.5 m (the datasheet's range 0.8-4 m)"),
        _structured_light(
            "xtion", 0.5, 4.5,
            "built-in: Asus Xtion PRO / PRO LIVE, PrimeSense Carmine 1.08: the PS1080 design "
            "of the Kinect v1 (Nguyen et al. 2012; Khoshelham & Oude Elberink 2012); evidence "
            "to 4.5 m (datasheet range 0.8-3.5 m)"),
        _structured_light(
            "orbbec_astra", 0.6, 4.5,
            "built-in: Orbbec Astra / Astra Pro (structured light, 7.5 cm baseline; datasheet: "
            "range 0.6-8 m, +-1-3 mm at 1 m), modelled on the PS1080 figures; evidence to "
            "4.5 m as for them"),
        _stereo("realsense_d415", 0.055, 65.0, 848, 0.3, 4.0,
                "built-in: Intel RealSense D415 (baseline 55 mm, HFOV 65 deg at 848 px, ideal "
                "range 0.5-3 m; datasheet) with Intel's depth RMS error formula, subpixel "
                "0.08"),
        _stereo("realsense_d435", 0.050, 87.0, 848, 0.3, 4.0,
                "built-in: Intel RealSense D435 / D435i (baseline 50 mm, HFOV 87 deg at 848 px, "
                "ideal range 0.3-3 m; datasheet) with Intel's depth RMS error formula, "
                "subpixel 0.08"),
        _stereo("realsense_d405", 0.018, 87.0, 848, 0.07, 1.0,
                "built-in: Intel RealSense D405 (baseline 18 mm, HFOV 87 deg at 848 px, ideal "
                "range 7-50 cm; datasheet) with Intel's depth RMS error formula, subpixel 0.08; "
                "evidence to 1 m"),
        _stereo("realsense_d455", 0.095, 87.0, 848, 0.5, 6.0,
                "built-in: Intel RealSense D455 (baseline 95 mm, HFOV 87 deg at 848 px, ideal "
                "range 0.6-6 m; datasheet) with Intel's depth RMS error formula, subpixel "
                "0.08"),
        NoiseProfile(
            name="azure_kinect", principle="time_of_flight", axial_m=(0.001, 0.001, 0.0),
            step_per_m=0.0, min_range_m=0.5, max_range_m=3.86, shadow_baseline_m=0.0,
            edge_px=2,
            source="built-in: Microsoft Azure Kinect DK, NFOV unbinned (datasheet: random "
                   "error <= 17 mm std, typically 1-3 mm; Toelgyessy et al., Sensors 21(2) "
                   "2021): 1 mm + 0.1 % of z"),
    )
}
#: The nearest depth used unless told (metres; :attr:`NoiseProfile.near_m`): Kinect-class
#: cameras read nothing useful nearer (their profiles say 0.5 m; what they give at 0.4-0.5 m
#: is kept).
DEFAULT_NEAR_M = 0.4
#: The profile of a camera nobody named: the Kinect v1 (the noise of every PrimeSense design).
DEFAULT_PROFILE = "kinect_v1"


def builtin_profile(name: str) -> NoiseProfile:
    """A built-in profile by name; :class:`BadValue` listing the known ones otherwise."""
    try:
        return BUILTIN[name]
    except (KeyError, TypeError):
        raise BadValue("camera", "profile", name,
                       f"one of the built-in profiles ({', '.join(sorted(BUILTIN))})") from None


#: The profile named by the camera itself: the built-in one of the model its driver reports
#: (:func:`profile_for_camera`), :data:`DEFAULT_PROFILE` when it reports none (a recording, an
#: image folder, a bag) or one without a built-in profile.
AUTO_PROFILE = "auto"
#: A camera model as its driver names it (a pattern) -> its built-in profile.
_CAMERA_MODELS = (
    (r"\bD405\b", "realsense_d405"), (r"\bD415\b", "realsense_d415"),
    (r"\bD43[05](?:i|f|if)?\b", "realsense_d435"), (r"\bD45[5-7]f?\b", "realsense_d455"),
    (r"Azure Kinect", "azure_kinect"),
    (r"\bAstra", "orbbec_astra"), (r"Xtion|Carmine|PrimeSense|PS1080", "xtion"),
    (r"Kinect", "kinect_v1"),
)


def profile_for_camera(model: str | None) -> str:
    """The built-in profile of a camera ``model`` as its driver names it ("Intel RealSense
    D435", "PS1080", "Kinect"); :data:`DEFAULT_PROFILE` for no model or an unknown one (a
    warning for a camera named but unknown: its noise may be far from the default's)."""
    for pattern, name in _CAMERA_MODELS:
        if model and re.search(pattern, model, re.IGNORECASE):
            return name
    if model and model != UNNAMED_CAMERA:
        log.warning("camera %r has no built-in noise profile: %s used; measure it with "
                    "`robot-change calibrate` or name one ([camera] profile, --profile)",
                    model, DEFAULT_PROFILE)
    return DEFAULT_PROFILE


def resolve_profile(name: str = DEFAULT_PROFILE, path=None,
                    camera: str | None = None) -> NoiseProfile:
    """The profile to use: the measured one in the file ``path`` when given (it wins), else
    the built-in ``name``; ``"auto"``: the built-in one of the ``camera`` model."""
    if path is not None:
        return NoiseProfile.load(path)
    return builtin_profile(profile_for_camera(camera) if name == AUTO_PROFILE else name)


@functools.lru_cache(maxsize=16)
def sigma_table(profile: NoiseProfile) -> np.ndarray:
    """:meth:`NoiseProfile.kernel_table` of ``profile``, read-only, made once per profile."""
    table = profile.kernel_table()
    table.setflags(write=False)
    return table
