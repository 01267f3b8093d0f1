"""The configuration's keys: checkers that turn a TOML value into the value kept, or a
:class:`~robot_change.errors.BadValue` (every check is :mod:`robot_change.validate`'s), the
field that carries one (:func:`_key`), and the frozen section that runs them
(:class:`_Section`, which rewords a BadValue as a ConfigError).  Used by
:mod:`robot_change.service.config`."""

from __future__ import annotations

import dataclasses
import functools
import ipaddress
from collections.abc import Callable
from typing import Any, ClassVar

from hw.depth import parse_uri
from hw.errors import UriError
from robot_change import validate
from robot_change.change.scene import SceneParams
from robot_change.cloud.chain import CloudParams
from robot_change.errors import BadValue, ConfigError
from robot_change.link.protocol import PARAM_BY_NAME

# checkers: (section, key, value from TOML) -> value kept (converted), or BadValue (every check
# is robot_change.validate's; _Section re-words a BadValue as a ConfigError)

Check = Callable[[str, str, Any], Any]


def _int(lo: int, hi: int, unit: str = "") -> Check:
    return functools.partial(validate.whole, low=lo, high=hi, unit=unit)


def _float(lo: float, hi: float, unit: str = "", *, lo_open: bool = False) -> Check:
    return functools.partial(validate.number, low=lo, high=hi, unit=unit, low_open=lo_open)


def _lower(value: Any) -> Any:
    return value.lower() if isinstance(value, str) else value


def _choice(options: tuple[Any, ...]) -> Check:
    def check(owner: str, name: str, value: Any) -> Any:
        return validate.choice(owner, name, _lower(value), options)
    return check


def _text(owner: str, name: str, value: Any) -> str:
    return validate.text(owner, name, value, non_empty=True, no_nul=True)


def _depth_uri(owner: str, name: str, value: Any) -> str:
    text = _text(owner, name, value)
    try:
        parse_uri(text)
    except UriError as exc:
        raise BadValue(owner, name, value, f"a depth URI such as 'openni2://', "
                       f"'openni2://SERIAL', 'oni:FILE.oni', 'images:DIR/' or 'rosbag:BAG' "
                       f"({exc})") from None
    return text


def _address(owner: str, name: str, value: Any) -> str:
    text = _text(owner, name, value)
    try:
        ipaddress.ip_address(text)
    except ValueError:
        raise BadValue(owner, name, value, "an IP address of this machine: \"127.0.0.1\" (this "
                       "machine only), \"0.0.0.0\" (every network) or one interface's") from None
    return text


def _optional_text(owner: str, name: str, value: Any) -> str:
    return validate.text(owner, name, value, max_bytes=1024, non_empty=True, no_nul=True)


def _broker(owner: str, name: str, value: Any) -> str:
    validate.broker_url(owner, name, value)
    return value


def _triple(limit: float, unit: str, example: str) -> Check:
    def check(owner: str, name: str, value: Any) -> tuple[float, float, float]:
        if not isinstance(value, (list, tuple)) or len(value) != 3:
            raise BadValue(owner, name, value, f"three numbers, each within +-{limit}{unit}, "
                           f"e.g. {example}", wrong_type=True)
        return tuple(validate.number(owner, f"{name}[{i}]", v, -limit, limit, unit=unit)
                     for i, v in enumerate(value))  # type: ignore[return-value]
    return check


def _param(name: str) -> Check:
    """The range of the protocol's runtime parameter ``name`` (same bounds on the wire)."""
    p = PARAM_BY_NAME[name]
    if p.unit == "bool":
        return validate.flag
    return _int(p.minimum, p.maximum, f" {p.unit}")


def _library(params: type, owner: str) -> Callable[[str], Check]:
    """A key checked by the library's own parameter class (CloudParams, SceneParams: the
    bounds live in one place), built with only that key changed from the defaults."""
    defaults = params()

    def for_key(key: str) -> Check:
        def check(section: str, name: str, value: Any) -> Any:
            default = getattr(defaults, key)
            value = _lower(value)
            trial = {key: value}
            if key == "plane_up":
                if not isinstance(value, list):
                    raise BadValue(section, name, value, "an array of 3 numbers, e.g. "
                                   "[0, -1, 0] (camera frame, y down)", wrong_type=True)
                trial["plane_max_tilt_deg"] = 10.0
            elif key == "plane_max_tilt_deg":
                trial["plane_up"] = (0.0, -1.0, 0.0)
            try:
                checked = params(**trial)
            except BadValue as exc:
                raise BadValue(section, name, value, exc.allowed,
                               wrong_type=exc.wrong_type) from None
            return float(value) if isinstance(default, float) else getattr(checked, key)
        return check
    return for_key


_cloud = _library(CloudParams, "CloudParams")
_scene = _library(SceneParams, "SceneParams")


def _key(default: Any, check: Check, doc: str) -> Any:
    return dataclasses.field(default=default, metadata={"check": check, "doc": doc})


class _Section:
    """A frozen section; every field is checked (and converted) on construction."""

    NAME: ClassVar[str] = ""

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            value = getattr(self, f.name)
            if value is None and f.default is None:
                continue  # an optional key left out
            try:
                object.__setattr__(self, f.name, f.metadata["check"](self.NAME, f.name, value))
            except BadValue as bad:
                raise ConfigError(f"{self.NAME}.{f.name} = {_show(value)}: must be "
                                  f"{bad.allowed}") from None
        self._cross_check()

    def _cross_check(self) -> None:
        """Checks between keys of the section (override)."""


def _show(value: Any) -> str:
    """A value as TOML would spell it (true/false, quoted strings, arrays)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_show(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_show(v)}" for k, v in value.items()) + "}"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(value)
