"""The parameters a capture or a check runs with: the configuration's, with the wire's
parameter table (SET_PARAM) on top."""

from __future__ import annotations

import dataclasses

from robot_change.config import Config
from robot_change.errors import ConfigError, InputError

__all__ = ["change_params", "scene_params"]


def change_params(config: Config, params: dict[str, int]):
    """The :class:`robot_change.change.ChangeParams` of a check: the configuration's free-form
    ``[change]`` keys that name ChangeParams fields, and the wire's ``min_region_points``."""
    from robot_change.change import ChangeParams

    fields = {f.name for f in dataclasses.fields(ChangeParams)}
    extra = {k: v for k, v in dict(config.change.extra).items() if k in fields}
    extra["min_region_points"] = int(params["min_region_points"])
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
    if cloud.min_depth_m >= cloud.max_depth_m:
        cloud = base.cloud
    return dataclasses.replace(base, cloud=cloud)
