"""The parameters a capture or a check runs with: the configuration's, with the wire's
parameter table (SET_PARAM) on top; and the one check of a configuration that ``check-config``,
``run`` and a reload (SIGHUP) all go through (:func:`load_checked_config`)."""

from __future__ import annotations

import dataclasses
import difflib
import os
from pathlib import Path

from hw.depth import open_depth
from hw.errors import BackendUnavailable, HwError, UriError
from hw.serial_port import check_port_url
from robot_change.change.params import ChangeParams
from robot_change.errors import ConfigError, FleetError, InputError
from robot_change.export.foxglove import sdk
from robot_change.fleet.connection import tls_context
from robot_change.service.config import Config, load_config

__all__ = ["change_params", "check_config", "load_checked_config", "scene_params"]


def load_checked_config(path: str | os.PathLike, *, reload: bool = False) -> Config:
    """Read ``path`` (:func:`robot_change.service.config.load_config`) and :func:`check_config` it:
    what ``check-config`` accepts, ``run`` starts with and a reload takes, and nothing else
    (``reload``: an empty file is refused too)."""
    config = load_config(path, empty_ok=not reload)
    check_config(config)
    return config


def check_config(config: Config) -> None:
    """What the file alone cannot say: the library's own parameter checks on the values the
    daemon will run with (ChangeParams, SceneParams, the wire's parameter table), a state
    folder that is a folder the service can write (or create), and the library a live view
    needs (foxglove-sdk).  Raises :class:`ConfigError`."""
    where = str(config.path) if config.path is not None else "<config>"
    try:
        params = config.parameters()
        change_params(config, params)
        scene_params(config, params)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    _check_camera_source(where, config.camera.source)
    try:
        check_port_url(config.serial.port)
    except UriError as exc:
        raise ConfigError(f"{where}: serial.port = {config.serial.port!r}: {exc}") from None
    _check_state_dir(where, Path(config.store.state_dir), config)
    _check_fleet_files(where, config)
    if config.viz.live:
        try:
            sdk()
        except InputError as exc:
            raise ConfigError(f"{where}: viz.live = true: {exc}; or set viz.live = "
                              "false") from None


def _check_camera_source(where: str, uri: str) -> None:
    """The camera's URI as ``run`` opens it, without opening it: its backend found and its
    options understood.  A file that is missing or damaged is the camera's problem, told as a
    FAULT when it is opened (a recording may be on a disk mounted later)."""
    try:
        open_depth(uri)
    except (UriError, BackendUnavailable) as exc:
        raise ConfigError(f"{where}: camera.source = {uri!r}: {exc}") from None
    except HwError:
        pass


def _check_fleet_files(where: str, config: Config) -> None:
    """The fleet's TLS and password files are files this user can read (their content is
    read when the daemon connects; the password is never printed)."""
    for name, path in config.fleet.files.items():
        key = f"{where}: fleet.{name} = {path!r}"
        if not os.path.isfile(path):
            raise ConfigError(f"{key}: no such file")
        if not os.access(path, os.R_OK):
            raise ConfigError(f"{key}: not readable by this user (uid {os.getuid()}); the "
                              "service user must be able to read it")
    settings = config.fleet.settings() if config.fleet.enabled else None
    try:
        if settings is not None and settings.password_file is not None:
            settings.password()
        if settings is not None and settings.tls:  # the CA file holds certificates, ...
            tls_context(settings)
    except FleetError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def _check_state_dir(where: str, path: Path, config: Config) -> None:
    """``path`` is a writable folder, or one that can be made (its nearest existing parent is
    a writable folder), and so are the folders in it that the daemon must write (the
    references, their quarantine, the fleet's spool when it reports) where they exist.  (The
    reports' folder is not: one that cannot be written costs its files, never the service.)"""
    key = f"{where}: store.state_dir = {str(path)!r}"
    folders = [config.store.references, config.store.references / "quarantine"]
    if config.fleet.enabled:
        folders.append(path / "fleet-spool")
    for folder in folders:
        if folder.exists() and not (folder.is_dir() and os.access(folder, os.R_OK | os.W_OK
                                                                   | os.X_OK)):
            what = "is not a folder" if not folder.is_dir() else (
                f"is not readable and writable by this user (uid {os.getuid()})")
            raise ConfigError(f"{key}: {folder} {what}; the service's user must own it "
                              "(chown -R it to that user)")
    probe = path
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        raise ConfigError(f"{key}: {probe} is not a folder")
    if probe.exists() and not os.access(probe, os.W_OK | os.X_OK):
        what = "the folder" if probe == path else f"{path} does not exist and its parent {probe}"
        raise ConfigError(f"{key}: {what} is not writable by this user (uid {os.getuid()}); "
                          f"under systemd, StateDirectory= makes it")


def change_params(config: Config, params: dict[str, int]):
    """The :class:`robot_change.change.params.ChangeParams` of a check: the configuration's
    free-form ``[change]`` keys that name ChangeParams fields, and the wire's
    ``min_region_points`` and ``min_region_extent_mm`` (whose defaults are ChangeParams' own:
    one set of defaults)."""
    fields = {f.name for f in dataclasses.fields(ChangeParams)}
    for name in dict(config.change.extra):
        if name not in fields:
            near = difflib.get_close_matches(name, sorted(fields), n=1, cutoff=0.6)
            hint = f"; did you mean change.{near[0]}?" if near else ""
            raise ConfigError(f"change.{name}: unknown key of [change] (neither a key of the "
                              f"file's nor a field of ChangeParams){hint}")
    extra = {k: v for k, v in dict(config.change.extra).items() if k in fields}
    extra["min_region_points"] = int(params["min_region_points"])
    extra["min_region_extent_m"] = int(params["min_region_extent_mm"]) / 1000.0
    try:
        return ChangeParams(**extra)
    except InputError as exc:
        raise ConfigError(f"[change]: {exc}") from None


def scene_params(config: Config, params: dict[str, int]):
    """SceneParams of a new reference: the configuration's, with the wire's ``max_depth_mm``.
    (A check cleans its frames with its reference's parameters, so a changed ``max_depth_mm``
    applies to references captured after the change.)"""
    base = config.scene_params()
    cloud = dataclasses.replace(base.cloud, max_depth_m=params["max_depth_mm"] / 1000.0)
    if cloud.min_depth_m is not None and cloud.min_depth_m >= cloud.max_depth_m:
        cloud = base.cloud
    return dataclasses.replace(base, cloud=cloud)
