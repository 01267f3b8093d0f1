"""The daemon's configuration: TOML (``tomllib``) into frozen, validated dataclasses.

    config = load_config("/etc/robot-change/robot-change.toml")
    config.watch.watch_m, config.cloud.params(), config.parameters()

Sections: ``camera``, ``serial``, ``store``, ``cloud``, ``mixture``, ``change``, ``watch``,
``viz``, ``service``, ``fleet`` (off unless ``fleet.broker`` is set);
``systemd/robot-change.toml`` documents every key with its default.  Keys that are also runtime
parameters of the protocol (``robot_change.link.protocol.PARAMS``: ``watch_m``,
``fuse_frames``, ``max_depth_mm`` ...) have the same names, ranges and defaults, and
:meth:`Config.parameters` gives their values as the daemon's starting parameter table.

Every error is a :class:`ConfigError` naming the file, the dotted key, the value and what is
allowed; unknown sections and keys are errors too, with a did-you-mean suggestion.  A command
that fails on its configuration exits with :data:`EXIT_CONFIG`.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import math
import os
import re
import socket
import tomllib
import types
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

from robot_change import validate
from robot_change.change.mount import CameraMount
from robot_change.change.scene import SceneParams
from robot_change.cloud.chain import CloudParams
from robot_change.errors import ConfigError
from robot_change.export.live import DEFAULT_HOST, DEFAULT_PORT
from robot_change.fleet.connection import BrokerSettings
from robot_change.link.protocol import PARAM_BY_NAME, PARAMS
from robot_change.noise.profile import (
    AUTO_PROFILE,
    BUILTIN,
    DEFAULT_PROFILE,
    NoiseProfile,
    ProfileFileError,
    resolve_profile,
)
from robot_change.service.config_keys import (
    _address,
    _broker,
    _choice,
    _cloud,
    _depth_uri,
    _float,
    _int,
    _key,
    _optional_text,
    _param,
    _scene,
    _Section,
    _show,
    _text,
    _triple,
)
from robot_change.service.store import (
    DEFAULT_MAX_STATIONS,
    DEFAULT_MIN_FREE_MB,
    MAX_STATIONS_LIMIT,
)

#: The library's own defaults: the config file's defaults are these, not copies of them.
_CLOUD = CloudParams()
_SCENE = SceneParams()

__all__ = [
    "EXIT_CONFIG",
    "CameraConfig",
    "ChangeConfig",
    "CloudConfig",
    "Config",
    "FleetConfig",
    "MixtureConfig",
    "SerialConfig",
    "ServiceConfig",
    "StoreConfig",
    "VizConfig",
    "WatchConfig",
    "load_config",
]

#: Exit status of a command stopped by a bad configuration (sysexits.h EX_CONFIG).  The systemd
#: unit lists it in RestartPreventExitStatus=: restarting cannot fix a configuration file.
EXIT_CONFIG = 78

#: Per-check MCAP files kept by default (the newest; ~0.5 MB each for VGA depth).
DEFAULT_KEEP_CHECKS = 20
#: Baud rates a USB serial adapter and the base controller commonly agree on.
BAUD_RATES = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 921600, 1000000,
              2000000)
LOG_LEVELS = ("debug", "info", "warning", "error")


# ---------------------------------------------------------------------------------------------
# sections


@dataclasses.dataclass(frozen=True)
class CameraConfig(_Section):
    """The depth camera (or recording) the daemon reads."""

    NAME: ClassVar[str] = "camera"
    source: str = _key("openni2://", _depth_uri,
                       "depth URI: openni2:// (first camera), openni2://SERIAL, oni:FILE.oni, "
                       "realsense://, images:DIR/, rosbag:BAG, pcd:FILE.pcd, mkv:FILE.mkv")
    fuse_frames: int = _key(PARAM_BY_NAME["fuse_frames"].default, _param("fuse_frames"),
                            "depth frames fused (per-pixel median) per reference or check")
    min_valid_fraction: float = _key(_SCENE.min_valid_fraction, _scene("min_valid_fraction"),
                                     "a fused pixel needs readings in this fraction of the "
                                     "frames")
    read_timeout_s: float = _key(1.0, _float(0.0, 30.0, " seconds", lo_open=True),
                                 "longest wait for one frame before the camera counts as lost")
    mount_xyz_m: tuple = _key((0.0, 0.0, 0.0), _triple(10.0, " m", "[0.2, 0.0, 0.45]"),
                              "the camera on the base: its body frame (x forward, y left, z up) "
                              "in base_link, metres")
    mount_rpy_deg: tuple = _key((0.0, 0.0, 0.0),
                                _triple(180.0, " degrees", "[0.0, 10.0, 0.0] (tilted 10 deg down)"),
                                "the camera on the base: roll, pitch, yaw of its body frame in "
                                "base_link, degrees (a camera tilted down 10 deg: [0, 10, 0])")
    profile: str = _key(AUTO_PROFILE, _choice((AUTO_PROFILE, *BUILTIN)),
                        "the camera's noise, a built-in profile: " + ", ".join(BUILTIN)
                        + f"; {AUTO_PROFILE}: the one of the camera's model as its driver names "
                        f"it ({DEFAULT_PROFILE} when it names none: recordings, images, bags)")
    profile_file: str | None = _key(None, _text,
                             "a profile measured with `robot-change calibrate` (JSON); it wins "
                             "over profile; a relative path is taken from the config file's "
                             "folder")

    def mount(self) -> CameraMount:
        """The :class:`robot_change.change.mount.CameraMount` these keys describe."""
        return CameraMount(self.mount_xyz_m, self.mount_rpy_deg)

    def noise_profile(self, camera: str | None = None) -> NoiseProfile:
        """The camera's noise profile: the measured one in ``profile_file`` when set, else the
        built-in ``profile`` (``auto``: the one of the ``camera`` model the source reports);
        :class:`ProfileFileError` for a file that cannot be read."""
        return resolve_profile(self.profile, self.profile_file, camera)


@dataclasses.dataclass(frozen=True)
class SerialConfig(_Section):
    """The serial line to the base controller."""

    NAME: ClassVar[str] = "serial"
    port: str = _key("/dev/robot-base", _text,
                     "serial port: a device path (the udev rule's /dev/robot-base) or a pyserial "
                     "URL (socket://HOST:PORT, loop://)")
    baud: int = _key(115200, _choice(BAUD_RATES), "line speed in baud (8N1)")


@dataclasses.dataclass(frozen=True)
class StoreConfig(_Section):
    """Where station references are kept."""

    NAME: ClassVar[str] = "store"
    state_dir: str = _key("/var/lib/robot-change", _text,
                          "folder of the station references (systemd's StateDirectory); a "
                          "relative path is taken from the config file's folder")
    max_stations: int = _key(DEFAULT_MAX_STATIONS, _int(1, MAX_STATIONS_LIMIT),
                             "a new station beyond this many is refused (FAULT STORAGE_ERROR)")
    min_free_mb: int = _key(DEFAULT_MIN_FREE_MB, _int(0, 10**7, " MB"),
                            "a capture that would leave less free on the disk is refused (FAULT "
                            "STORAGE_ERROR)")

    @property
    def references(self) -> Path:
        """The folder a :class:`robot_change.service.store.ReferenceStore` uses."""
        return Path(self.state_dir) / "references"


@dataclasses.dataclass(frozen=True)
class CloudConfig(_Section):
    """Depth -> clean cloud (robot_change.cloud.chain.CloudParams; depth range as on the wire)."""

    NAME: ClassVar[str] = "cloud"
    leaf_m: float = _key(_CLOUD.leaf_m, _cloud("leaf_m"), "voxel size in metres")
    min_depth_mm: int | None = _key(None, _int(0, 10_000, " mm"),
                                    "nearer depth is not used (left out: the camera's, 400 mm "
                                    "or its near range where it reads nearer)")
    max_depth_mm: int = _key(PARAM_BY_NAME["max_depth_mm"].default, _param("max_depth_mm"),
                             "depth beyond this is not used")
    remove_outliers: bool = _key(_CLOUD.remove_outliers, _cloud("remove_outliers"),
                                 "statistical outlier removal on the voxel cloud")
    outlier_k: int = _key(_CLOUD.outlier_k, _cloud("outlier_k"),
                          "neighbours per voxel in outlier removal")
    outlier_alpha: float = _key(_CLOUD.outlier_alpha, _cloud("outlier_alpha"),
                                "a voxel is an outlier beyond mean + alpha * std of the "
                                "neighbour distances")
    outlier_cap_leaves: float = _key(_CLOUD.outlier_cap_leaves, _cloud("outlier_cap_leaves"),
                                     "... and within this many leaves it never is")
    remove_plane: bool = _key(_CLOUD.remove_plane, _cloud("remove_plane"),
                              "remove the dominant plane (floor)")
    plane_distance_m: float = _key(_CLOUD.plane_distance_m, _cloud("plane_distance_m"),
                                   "plane inlier distance in metres")
    plane_iterations: int = _key(_CLOUD.plane_iterations, _cloud("plane_iterations"),
                                 "most RANSAC triples")
    plane_seed: int = _key(_CLOUD.plane_seed, _cloud("plane_seed"),
                           "RANSAC seed (same seed, same plane)")
    plane_min_inliers: int = _key(_CLOUD.plane_min_inliers, _cloud("plane_min_inliers"),
                                  "a plane needs this many voxels")
    plane_up: tuple[float, float, float] | None = _key(
        None, _cloud("plane_up"), "camera-frame up vector; only planes within "
        "plane_max_tilt_deg of it count (set both or neither)")
    plane_max_tilt_deg: float | None = _key(None, _cloud("plane_max_tilt_deg"),
                                            "largest tilt of the plane from plane_up, degrees")

    def _cross_check(self) -> None:
        if self.min_depth_mm is not None and self.min_depth_mm >= self.max_depth_mm:
            raise ConfigError(f"cloud.min_depth_mm = {self.min_depth_mm}: must be below "
                              f"cloud.max_depth_mm = {self.max_depth_mm}")
        if (self.plane_up is None) != (self.plane_max_tilt_deg is None):
            given, missing = (("plane_up", "plane_max_tilt_deg") if self.plane_up is not None
                              else ("plane_max_tilt_deg", "plane_up"))
            raise ConfigError(f"cloud.{given} = {_show(getattr(self, given))}: must come with "
                              f"cloud.{missing} (set both or neither)")

    def params(self):
        """The :class:`robot_change.cloud.chain.CloudParams` these keys describe."""
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        near_mm = values.pop("min_depth_mm")
        values["min_depth_m"] = None if near_mm is None else near_mm / 1000.0
        values["max_depth_m"] = values.pop("max_depth_mm") / 1000.0
        return CloudParams(**values)


@dataclasses.dataclass(frozen=True)
class MixtureConfig(_Section):
    """The Gaussian mixture fitted to a cloud (robot_change.change.scene.SceneParams ->
    robot_change.mixture.model.fit_mixture)."""

    NAME: ClassVar[str] = "mixture"
    criterion: str = _key(_SCENE.criterion, _scene("criterion"),
                          "model-selection criterion that picks the number of components")
    max_components: int = _key(_SCENE.max_components, _scene("max_components"),
                               "most components of one mixture")
    tol: float = _key(_SCENE.tol, _scene("tol"), "EM stops when the mean log-likelihood per point "
                      "changes by less")
    max_iter: int = _key(_SCENE.max_iter, _scene("max_iter"), "most iterations of one EM run")
    seed: int = _key(_SCENE.seed, _scene("seed"),
                     "seed of the random subsets (same seed, same fit)")
    search_points: int = _key(_SCENE.search_points, _scene("search_points"),
                              "the split search runs on a random subset of this many points")


#: Free-form keys of [change]: snake_case names, numbers or booleans.
_FREE_KEY = re.compile(r"[a-z][a-z0-9_]{0,63}\Z")


@dataclasses.dataclass(frozen=True)
class ChangeConfig(_Section):
    """Thresholds of change detection.  The protocol's three are checked here; further keys are
    fields of :class:`robot_change.change.params.ChangeParams`, kept in ``extra`` (snake_case
    names, finite numbers or booleans, no near-miss of a known key) and checked against
    ChangeParams by :func:`robot_change.service.params.check_config` (an unknown one is
    refused with a hint)."""

    NAME: ClassVar[str] = "change"
    min_region_points: int = _key(PARAM_BY_NAME["min_region_points"].default,
                                  _param("min_region_points"),
                                  "changed regions with fewer points are ignored")
    min_region_extent_mm: int = _key(PARAM_BY_NAME["min_region_extent_mm"].default,
                                     _param("min_region_extent_mm"),
                                     "changed regions smaller than this are ignored")
    pause_on_change: bool = _key(bool(PARAM_BY_NAME["pause_on_change"].default),
                                 _param("pause_on_change"),
                                 "true: a change raises PAUSE; false: report only")
    extra: Mapping[str, float | int | bool] = dataclasses.field(
        default_factory=lambda: types.MappingProxyType({}),
        metadata={"check": lambda _section, _key, value: value,
                  "doc": "further thresholds of the change step"})

    def _cross_check(self) -> None:
        known = [f.name for f in dataclasses.fields(self) if f.name != "extra"]
        clean = {}
        for name, value in dict(self.extra).items():
            where = f"change.{name} = {_show(value)}"
            if not isinstance(name, str) or not _FREE_KEY.match(name):
                raise ConfigError(f"{where}: a threshold name is snake_case (a-z, 0-9, _)")
            elsewhere = _ALL_KEYS.get(name)
            if name in known or name == "extra":
                raise ConfigError(f"{where}: '{name}' is not a free-form threshold")
            if elsewhere:
                raise ConfigError(f"{where}: '{name}' belongs in [{elsewhere}]")
            near = difflib.get_close_matches(name, known, n=1, cutoff=0.85)
            if near:
                raise ConfigError(f"{where}: unknown key; did you mean change.{near[0]}? "
                                  "(free-form thresholds must not be near-misses of known keys)")
            if not (isinstance(value, (bool, int))
                    or (isinstance(value, float) and math.isfinite(value))):
                raise ConfigError(f"{where}: a free-form threshold must be a finite number or "
                                  "true/false")
            clean[name] = value
        object.__setattr__(self, "extra", types.MappingProxyType(clean))


@dataclasses.dataclass(frozen=True)
class WatchConfig(_Section):
    """WATCH: a change must persist over watch_m of the last watch_n checks."""

    NAME: ClassVar[str] = "watch"
    watch_m: int = _key(PARAM_BY_NAME["watch_m"].default, _param("watch_m"),
                        "WATCH pauses when a change is seen in watch_m ...")
    watch_n: int = _key(PARAM_BY_NAME["watch_n"].default, _param("watch_n"),
                        "... of the last watch_n checks")
    check_interval_ms: int = _key(PARAM_BY_NAME["check_interval_ms"].default,
                                  _param("check_interval_ms"), "time between two WATCH checks")

    def _cross_check(self) -> None:
        if self.watch_m > self.watch_n:
            raise ConfigError(f"watch.watch_m = {self.watch_m}: must be <= watch.watch_n = "
                              f"{self.watch_n} (M of the last N checks)")


@dataclasses.dataclass(frozen=True)
class VizConfig(_Section):
    """Views of the checks for Foxglove (robot_change.export): per-check MCAP files beside the
    last check, and a live WebSocket server."""

    NAME: ClassVar[str] = "viz"
    keep_checks: int = _key(DEFAULT_KEEP_CHECKS, _int(0, 100_000),
                            "every CHECK is written as an MCAP file to <state_dir>/reports/"
                            "checks/; the newest this many are kept (0: none written)")
    live: bool = _key(False, validate.flag,
                      "serve every CHECK live over the Foxglove WebSocket protocol")
    live_host: str = _key(DEFAULT_HOST, _address, "address the live view listens on")
    live_port: int = _key(DEFAULT_PORT, _int(0, 65535), "TCP port of the live view (0: any "
                          "free port, logged at start)")


@dataclasses.dataclass(frozen=True)
class ServiceConfig(_Section):
    """The daemon itself."""

    NAME: ClassVar[str] = "service"
    watchdog: bool = _key(True, validate.flag,
                          "send WATCHDOG=1 when systemd's WatchdogSec= asks for it (false only "
                          "for debugging: systemd then kills the service after WatchdogSec)")
    log_level: str = _key("info", _choice(LOG_LEVELS), "journal verbosity")
    warmup_timeout_s: float = _key(240.0, _float(10.0, 3600.0, " seconds"),
                                   "longest wait for the numba kernels at start (a cold cache "
                                   "compiles them: ~30 s on 2 x86 cores); past it the start is a "
                                   "stall: FAULT STALLED to the base, exit 70")


@dataclasses.dataclass(frozen=True)
class FleetConfig(_Section):
    """The fleet: checks, changes and health on an MQTT broker (robot_change.fleet).  Off
    while ``broker`` is unset; then no other key may differ from its default."""

    NAME: ClassVar[str] = "fleet"
    broker: str | None = _key(None, _broker,
                              "the broker: mqtt://HOST[:PORT] (port 1883) or mqtts://HOST[:PORT] "
                              "(TLS, port 8883); unset: the fleet is off")
    robot_id: str | None = _key(None, functools.partial(validate.plain_name,
                                                        max_chars=validate.MAX_ROBOT_ID),
                                "this robot's name in the topics (default: the host name)")
    topic_prefix: str = _key("robot-change", validate.topic_prefix,
                             "first topic levels: <prefix>/<robot_id>/status, /checks/<station>, "
                             "/changes/<station>, /command, /reply")
    ca_file: str | None = _key(None, _text, "mqtts: CA certificates (PEM) the broker's "
                               "certificate must be signed by (default: the system's)")
    cert_file: str | None = _key(None, _text, "mqtts: this robot's client certificate (PEM)")
    key_file: str | None = _key(None, _text, "mqtts: the client certificate's key (PEM, "
                                "unencrypted)")
    username: str | None = _key(None, _optional_text, "user name at the broker")
    password_file: str | None = _key(None, _text, "a file holding the password alone (never "
                                     "in this file, never printed)")
    spool_mb: float = _key(64.0, _float(0.01, 100_000.0, " MB"),
                           "reports kept on disk while the broker is out of reach; when full, "
                           "the oldest are dropped and counted")
    keepalive_s: int = _key(30, _int(5, 3600, " seconds"),
                            "MQTT keep-alive: the broker marks the robot offline (Last Will) "
                            "after 1.5 times this without a word")

    @property
    def enabled(self) -> bool:
        return self.broker is not None

    def _cross_check(self) -> None:
        defaults = {f.name: f.default for f in dataclasses.fields(self)}
        if self.broker is None:
            for name, default in defaults.items():
                if getattr(self, name) != default:
                    raise ConfigError(f"fleet.{name} = {_show(getattr(self, name))}: needs "
                                      "fleet.broker (the fleet is off without it)")
            return
        tls = validate.broker_url("fleet", "broker", self.broker)[0] == "mqtts"
        for name in ("ca_file", "cert_file", "key_file"):
            if getattr(self, name) is not None and not tls:
                raise ConfigError(f"fleet.{name} = {_show(getattr(self, name))}: needs an "
                                  f"mqtts:// broker (fleet.broker = {_show(self.broker)})")
        if (self.cert_file is None) != (self.key_file is None):
            given = "cert_file" if self.cert_file is not None else "key_file"
            other = "key_file" if given == "cert_file" else "cert_file"
            raise ConfigError(f"fleet.{given} = {_show(getattr(self, given))}: must come with "
                              f"fleet.{other} (set both or neither)")
        if self.password_file is not None and self.username is None:
            raise ConfigError(f"fleet.password_file = {_show(self.password_file)}: needs "
                              "fleet.username")
        if self.robot_id is None:
            host = socket.gethostname().split(".")[0]
            if not validate.is_station(host) or len(host) > validate.MAX_ROBOT_ID:
                raise ConfigError(f"fleet.robot_id: not set, and the host name {host!r} cannot "
                                  "name the robot in a topic; set fleet.robot_id (1..64 ASCII "
                                  "letters, digits, '_' or '-')")
            object.__setattr__(self, "robot_id", host)

    def settings(self) -> BrokerSettings:
        """The :class:`robot_change.fleet.connection.BrokerSettings` these keys describe."""
        if self.broker is None:
            raise ConfigError("the fleet is off: fleet.broker is not set")
        return BrokerSettings(self.broker, self.ca_file, self.cert_file, self.key_file,
                              self.username, self.password_file, self.keepalive_s)

    @property
    def files(self) -> dict[str, str]:
        """The files the fleet reads (key -> path), for the configuration check."""
        return {name: getattr(self, name) for name in
                ("ca_file", "cert_file", "key_file", "password_file")
                if getattr(self, name) is not None}


_SECTIONS: tuple[type[_Section], ...] = (CameraConfig, SerialConfig, StoreConfig, CloudConfig,
                                          MixtureConfig, ChangeConfig, WatchConfig, VizConfig,
                                          ServiceConfig, FleetConfig)
#: key -> the section it belongs to (each key name is used by one section only).
_ALL_KEYS: dict[str, str] = {
    f.name: cls.NAME for cls in _SECTIONS
    for f in dataclasses.fields(cls) if f.name != "extra"  # type: ignore[arg-type]
}


@dataclasses.dataclass(frozen=True)
class Config:
    """The whole configuration; each section a frozen dataclass (defaults where absent)."""

    camera: CameraConfig = dataclasses.field(default_factory=CameraConfig)
    serial: SerialConfig = dataclasses.field(default_factory=SerialConfig)
    store: StoreConfig = dataclasses.field(default_factory=StoreConfig)
    cloud: CloudConfig = dataclasses.field(default_factory=CloudConfig)
    mixture: MixtureConfig = dataclasses.field(default_factory=MixtureConfig)
    change: ChangeConfig = dataclasses.field(default_factory=ChangeConfig)
    watch: WatchConfig = dataclasses.field(default_factory=WatchConfig)
    viz: VizConfig = dataclasses.field(default_factory=VizConfig)
    service: ServiceConfig = dataclasses.field(default_factory=ServiceConfig)
    fleet: FleetConfig = dataclasses.field(default_factory=FleetConfig)
    #: the file it was read from (None for defaults); not part of equality
    path: Path | None = dataclasses.field(default=None, compare=False)
    #: the keys that file sets, "section.key" (a reload refuses a file that lost one: cut
    #: short?); a section without keys counts as "section"
    keys: frozenset[str] = dataclasses.field(default=frozenset(), compare=False)

    @classmethod
    def default(cls) -> Config:
        """Every key at its default (what an empty file gives)."""
        return cls()

    def scene_params(self):
        """The :class:`robot_change.change.scene.SceneParams` a reference or check is built with."""
        m = self.mixture
        return SceneParams(cloud=self.cloud.params(), criterion=m.criterion,
                           max_components=m.max_components, tol=m.tol, max_iter=m.max_iter,
                           seed=m.seed, search_points=m.search_points,
                           min_valid_fraction=self.camera.min_valid_fraction)

    def parameters(self) -> dict[str, int]:
        """The protocol's runtime parameters (``PARAMS`` names -> values) as configured: the
        daemon's parameter table at start; SET_PARAM changes it until the next restart."""
        values: dict[str, int] = {}
        for p in PARAMS:
            section = getattr(self, _ALL_KEYS[p.name])
            values[p.name] = int(getattr(section, p.name))
        return values

    def as_toml(self) -> str:
        """The effective settings as a TOML file would spell them (every key, defaults too)."""
        lines = []
        for section, table in self.as_dict().items():
            lines.append(f"[{section}]")
            lines.extend(f"{key} = {_show(value)}" for key, value in table.items())
            lines.append("")
        return "\n".join(lines)

    def as_dict(self) -> dict[str, dict[str, Any]]:
        """Section -> key -> value (optional keys left out when unset), e.g. to print."""
        out: dict[str, dict[str, Any]] = {}
        for cls in _SECTIONS:
            section = getattr(self, cls.NAME)
            table: dict[str, Any] = {}
            for f in dataclasses.fields(section):
                value = getattr(section, f.name)
                if f.name == "extra":
                    table.update(value)
                elif value is not None:
                    table[f.name] = list(value) if isinstance(value, tuple) else value
            out[cls.NAME] = table
        return out


# ---------------------------------------------------------------------------------------------
# loading


def _suggest(name: str, candidates: list[str]) -> str:
    near = difflib.get_close_matches(name, candidates, n=1, cutoff=0.6)
    return f"; did you mean {near[0]!r}?" if near else ""


def _read(path: Path) -> dict[str, Any]:
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such configuration file; copy the example "
                          "systemd/robot-change.toml there (docs/deployment.md)") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a folder, not a configuration file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the configuration file ({exc.strerror}); "
                          "check its permissions (the service user must be able to read "
                          "it)") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        column = exc.start - (raw.rfind(b"\n", 0, exc.start) + 1) + 1
        raise ConfigError(f"{path}: not UTF-8 text (byte {raw[exc.start]:#04x} at line {line}, "
                          f"column {column}); TOML files are UTF-8") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        # "... (at line L, column C)"
        raise ConfigError(f"{path}: invalid TOML: {exc}") from None


def config_from_dict(data: Mapping[str, Any], source: str = "<config>",
                     base_dir: Path | None = None) -> Config:
    """Build a :class:`Config` from parsed TOML; errors are prefixed with ``source``."""
    sections: dict[str, _Section] = {}
    names = [cls.NAME for cls in _SECTIONS]
    for name, table in data.items():
        if name not in names:
            hint = (f"; '{name}' is a key of [{_ALL_KEYS[name]}]" if name in _ALL_KEYS
                    else _suggest(name, names))
            raise ConfigError(f"{source}: unknown section [{name}] (known: "
                              f"{', '.join(names)}){hint}")
        if not isinstance(table, dict):
            raise ConfigError(f"{source}: {name} = {_show(table)}: must be a table, "
                              f"written [{name}] followed by its keys")
    for cls in _SECTIONS:
        table = dict(data.get(cls.NAME, {}))
        fields = {f.name for f in dataclasses.fields(cls)} - {"extra"}  # type: ignore[arg-type]
        kwargs: dict[str, Any] = {}
        extra: dict[str, Any] = {}
        for key, value in table.items():
            if key in fields:
                kwargs[key] = value
            elif cls is ChangeConfig:
                extra[key] = value
            else:
                where = f"{cls.NAME}.{key} = {_show(value)}"
                hint = _suggest(key, sorted(fields))
                if key in _ALL_KEYS:  # e.g. [viz] port: live_port, or serial.port
                    hint = (f"{hint} (or '{key}' of [{_ALL_KEYS[key]}])" if hint
                            else f"; it belongs in [{_ALL_KEYS[key]}]")
                raise ConfigError(f"{source}: {where}: unknown key (known in [{cls.NAME}]: "
                                  f"{', '.join(sorted(fields))}){hint}")
        if extra:
            kwargs["extra"] = extra
        try:
            sections[cls.NAME] = cls(**kwargs)
        except ConfigError as exc:
            raise ConfigError(f"{source}: {exc}") from None
    store = sections["store"]
    if base_dir is not None and not os.path.isabs(store.state_dir):
        sections["store"] = dataclasses.replace(store, state_dir=str(base_dir / store.state_dir))
    camera = sections["camera"]
    if camera.profile_file:
        if base_dir is not None and not os.path.isabs(camera.profile_file):
            camera = dataclasses.replace(camera, profile_file=str(base_dir / camera.profile_file))
            sections["camera"] = camera
        try:
            camera.noise_profile()
        except ProfileFileError as exc:
            raise ConfigError(f"{source}: camera.profile_file = {_show(camera.profile_file)}: "
                              f"{exc}") from None
    fleet = sections["fleet"]
    if base_dir is not None and fleet.files:  # a relative path: from the file's folder
        sections["fleet"] = dataclasses.replace(fleet, **{
            name: str(base_dir / path) for name, path in fleet.files.items()
            if not os.path.isabs(path)})
    return Config(**sections)  # type: ignore[arg-type]


def load_config(path: str | os.PathLike, *, empty_ok: bool = True) -> Config:
    """Read and check a TOML configuration file (see the module docstring).

    Raises :class:`ConfigError` (file, dotted key, value, what is allowed) for a missing,
    unreadable or invalid file, an unknown section or key, or a value out of range; and, with
    ``empty_ok=False`` (a reload), for a file that holds no key at all (half-written, or
    emptied by mistake: it would mean every default, ``openni2://`` as the camera).
    """
    path = Path(path)
    data = _read(path)
    if not data and not empty_ok:
        raise ConfigError(f"{path}: holds no key at all (a half-written or emptied file?); an "
                          "empty configuration is refused on a reload")
    config = config_from_dict(data, str(path), base_dir=path.resolve().parent)
    keys: set[str] = set()
    for section, table in data.items():
        if isinstance(table, dict) and table:
            keys.update(f"{section}.{key}" for key in table)
        else:
            keys.add(section)
    return dataclasses.replace(config, path=path, keys=frozenset(keys))
