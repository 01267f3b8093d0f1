"""What the command implementations share: the bundled fixtures, depth frames read from a URI
(fused, with their intrinsics and the camera model they name), the noise profile and the cloud
parameters a command's options ask for, and one-line JSON output."""

from __future__ import annotations

import argparse
import importlib.util
import logging
from pathlib import Path
from typing import Any

import numpy as np

from hw.depth import DepthFrame, Intrinsics, open_depth
from robot_change import json_text
from robot_change.errors import InputError

log = logging.getLogger("robot_change.cli")  # the CLI's log lines keep their logger's name


def _fixtures_folder() -> Path:
    """The bundled fixtures: the ``sim_fixtures`` package (installed with the demo's and the
    bench's recordings as package data, or the checkout's), found without importing it."""
    spec = importlib.util.find_spec("sim_fixtures")
    if spec is not None and spec.origin:
        return Path(spec.origin).resolve().parent
    return Path(__file__).resolve().parents[2] / "sim_fixtures"


#: The bundled fixtures (the recordings ``demo`` and ``bench`` use).
SIM_FIXTURES = _fixtures_folder()
#: The VGA frame of a furnished room (Kinect noise model) used by ``demo`` and ``bench``.
DEMO_FRAME = SIM_FIXTURES / "frames" / "room_vga.png"
#: The bundled scene ``bench`` times change detection on (a box appears in an office).
DETECT_SCENE = "office_box_added"


def _bundled(path: Path) -> str:
    if not path.exists():
        raise InputError(
            f"the bundled fixture {path} is missing (it ships with robot-change: reinstall "
            "it), or pass --source URI to use your own depth"
        )
    return str(path)


def _read_depth(uri: str, frames: int, intrinsics: str | None
                ) -> tuple[np.ndarray, Intrinsics, int]:
    """Read up to ``frames`` frames from ``uri``; several are fused by per-pixel median.

    Returns ((H, W) uint16 mm, intrinsics, number of frames read).
    """
    from robot_change.change.scene import SceneParams
    from robot_change.cloud.fusion import fuse_depth

    read = _read_frames(uri, frames)
    camera = _camera(read, intrinsics)
    if len(read) == 1:
        return read[0].depth, camera, 1
    # as a scene is fused: a pixel needs readings in enough frames, so edge flicker stays out
    stack = np.stack([frame.depth for frame in read])
    return fuse_depth(stack, min_valid=SceneParams().min_valid(len(read))), camera, len(read)


def _camera(frames: list[DepthFrame], intrinsics: str | None) -> Intrinsics:
    """The frames' intrinsics, or ``--intrinsics fx,fy,cx,cy`` for their image size."""
    camera = frames[0].intrinsics
    if intrinsics:
        camera = Intrinsics.parse(intrinsics, camera.width, camera.height)
    return camera


def _cloud_params(args: argparse.Namespace):
    from robot_change.cloud.chain import CloudParams

    if getattr(args, "leaf", None) is None:
        return CloudParams()
    try:
        return CloudParams(leaf_m=args.leaf)
    except InputError as exc:  # name the option, not the field
        raise InputError(f"--leaf {args.leaf:g}: {str(exc).split(': ', 1)[-1]}") from None


def _out_folder(text: str | None) -> Path | None:
    """``--out`` of a command that writes a folder, made now (before the work; None when not
    given); an :class:`InputError` names a file in the way."""
    if not text:
        return None
    out = Path(text)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: is a file; this command writes a folder of files (give "
                         "a folder's name; it is made if missing)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--out {out}: cannot make the folder ({exc.strerror or exc})") from None
    return out


def _print_json(payload: dict[str, Any]) -> None:
    print(json_text.dumps(payload, indent=None, sort_keys=False))


class DefaultFrames(int):
    """A ``--frames`` the user did not give (the command's default): a source shorter than it,
    such as one image or one cloud, is used as it is without a warning."""


def _read_frames(uri: str, frames: int) -> list[DepthFrame]:
    """Up to ``frames`` frames from a depth URI (fewer when a recording is shorter: a warning
    when ``frames`` was asked for, not a :class:`DefaultFrames`).  The camera's model, when
    the source names one, is kept in ``_CAMERA_MODEL[uri]`` (the ``auto`` noise profile)."""
    read: list[DepthFrame] = []
    with open_depth(uri) as source:
        _CAMERA_MODEL[uri] = (getattr(source, "info", None) or {}).get("name") or None
        for frame in source:
            read.append(frame)
            if len(read) == frames:
                break
    if not read:
        raise InputError(f"{uri}: the source delivered no frame")
    if len(read) < frames:
        level = logging.INFO if isinstance(frames, DefaultFrames) else logging.WARNING
        log.log(level, "%s ended after %d of the %d frames asked for (--frames); using %d",
                uri, len(read), frames, len(read))
    return read


#: depth URI -> the camera model its source named (the ``auto`` profile of the frames read)
_CAMERA_MODEL: dict[str, str | None] = {}


def _profile(args: argparse.Namespace, uri: str | None = None):
    """``--profile``: a built-in profile's name, ``auto`` (that of the camera model the source
    ``uri`` named) or a profile file (robot_change.noise)."""
    from robot_change.noise.profile import resolve_profile

    name = args.profile
    if name.lower().endswith(".json") or "/" in name:
        return resolve_profile(path=name)
    return resolve_profile(name, camera=_CAMERA_MODEL.get(uri or ""))
