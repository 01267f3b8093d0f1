"""The commands on scenes: ``cloud`` (depth -> clean cloud), ``capture`` (a station
reference), ``calibrate`` (a camera's noise profile) and ``detect`` (what changed), with the
point files and summaries they write."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from hw.depth import open_depth
from hw.pointfile import write_points
from robot_change import json_text
from robot_change.change.mount import CameraMount
from robot_change.commands.common import (
    _CAMERA_MODEL,
    _camera,
    _cloud_params,
    _out_folder,
    _print_json,
    _profile,
    _read_depth,
    _read_frames,
)
from robot_change.export import APPEARED_RGB, DISAPPEARED_RGB

#: ``detect --exit-code``: the exit status of each outcome (2 stays "an error").
DETECT_EXIT = {"no_change": 0, "changed": 1, "not_at_station": 3}


def _describe_plane(plane) -> dict[str, Any] | None:
    """The removed plane as plain numbers (None when none was found)."""
    if not plane.found:
        return None
    return {
        "normal": [round(float(v), 4) for v in plane.normal],
        "distance_m": round(float(plane.offset), 4),
        "inliers": int(plane.n_inliers),
    }


#: Colours of the changed points in .pcd / .ply files (r, g, b, 0..255).
APPEARED_COLOR, DISAPPEARED_COLOR = (tuple(round(255 * c) for c in rgb)
                                     for rgb in (APPEARED_RGB, DISAPPEARED_RGB))


def _points_frame(fmt: str, mount: CameraMount | None) -> str:
    """The frame point files are written in: base_link for .pcd / .ply when the camera's
    mounting is known, else (and always for .npy, which cannot say it) the camera optical
    frame."""
    return "base_link" if mount is not None and fmt != "npy" else "camera_optical"


def _write_point_files(files: dict[Path, tuple[np.ndarray, tuple[int, int, int] | None]],
                       fmt: str, mount: CameraMount | None) -> tuple[list[str], str]:
    """Write each (M, 3) optical-frame point array to its path (ending in ``.fmt``) through
    :func:`hw.pointfile.write_points`, in :func:`_points_frame`; returns (paths, frame)."""
    frame = _points_frame(fmt, mount)
    pose = mount.base_from_optical() if frame == "base_link" else None
    written = []
    for path, (points, color) in files.items():
        moved = mount.to_base(points) if frame == "base_link" else points
        write_points(path, moved, frame=frame, pose=pose, color=color)
        written.append(str(path))
    return written, frame


def cmd_cloud(args: argparse.Namespace) -> int:
    """Depth -> clean cloud: print a summary, optionally save the points and a picture."""
    from robot_change.cloud.chain import clean_cloud

    started = time.perf_counter()
    mount = CameraMount.parse(args.mount) if args.mount else None
    params = _cloud_params(args)
    out_dir = _out_folder(args.out)
    depth, camera, n_frames = _read_depth(args.source, args.frames, args.intrinsics)
    cloud = clean_cloud(depth, camera, params)
    summary = {
        "source": args.source,
        "frames": n_frames,
        "size": [camera.width, camera.height],
        "valid_pixels": int(np.count_nonzero(depth)),
        "stage_counts": dict(cloud.stage_counts),
        "plane": _describe_plane(cloud.plane),
        "leaf_m": params.leaf_m,
        "timings_ms": {key: round(value, 2) for key, value in cloud.timings_ms.items()},
        "seconds": round(time.perf_counter() - started, 3),
    }
    if out_dir is not None:
        summary["files"], summary["frame"] = _write_point_files(
            {out_dir / f"cloud.{args.format}": (cloud.points, None)}, args.format, mount)
        if not args.no_picture:
            from robot_change.tools.report import draw_cloud

            picture = draw_cloud(depth, camera, cloud, out_dir / "cloud.png", title=args.source)
            summary["files"].append(str(picture))
    if args.json:
        _print_json(summary)
    else:
        _print_cloud_summary(summary)
    return 0


def _print_cloud_summary(summary: dict[str, Any]) -> None:
    width, height = summary["size"]
    valid = summary["valid_pixels"]
    print(f"source      {summary['source']}  ({summary['frames']} frame(s), {width}x{height})")
    print(f"valid       {valid} pixels ({100.0 * valid / (width * height):.1f} %)")
    counts = summary["stage_counts"]
    print("points      " + " -> ".join(f"{value} {key.replace('_', ' ')}"
                                       for key, value in counts.items() if key != "pixels"))
    plane = summary["plane"]
    if plane is None:
        print("plane       none found")
    else:
        print(f"plane       normal {plane['normal']}, {plane['distance_m']} m from the camera, "
              f"{plane['inliers']} voxels removed")
    timings = summary["timings_ms"]
    print("time        " + ", ".join(f"{key[:-3]} {value:.2f} ms"
                                      for key, value in timings.items()))
    for path in summary.get("files", []):
        print(f"wrote       {path}")


def _is_scene_file(target: str) -> bool:
    """A saved SceneModel (``*.npz``, or a file of another name that is a zip, as an .npz is:
    no depth file is) rather than a depth URI."""
    if target.lower().endswith(".npz"):
        return True
    try:
        with open(target, "rb") as file:
            return file.read(4) == b"PK\x03\x04"
    except OSError:  # a URI, a folder, a missing file: the depth source says what is wrong
        return False


def _scene_params(args: argparse.Namespace):
    from robot_change.change.scene import SceneParams

    return SceneParams(cloud=_cloud_params(args))


def _reference_scene(args: argparse.Namespace):
    """The reference as a SceneModel: loaded from a file (with the profile it was captured
    with), or built from frames of a URI."""
    from robot_change.change.scene import SceneModel, build_scene

    if _is_scene_file(args.reference):
        return SceneModel.load(args.reference)
    frames = _read_frames(args.reference, args.frames)
    return build_scene(frames, _scene_params(args), intrinsics=_camera(frames, args.intrinsics),
                       source=args.reference, noise=_profile(args, args.reference))


def _current_input(args: argparse.Namespace, reference):
    """The current epoch: (a saved SceneModel, its depth, its intrinsics, None), or (the fused
    depth of a URI's frames, that depth, the intrinsics to read it with, those again): the
    last is what the detector is told (a SceneModel carries its own)."""
    from robot_change.change.scene import SceneModel
    from robot_change.cloud.fusion import fuse_depth

    if _is_scene_file(args.current):
        scene = SceneModel.load(args.current)
        return scene, scene.depth, scene.intrinsics, None
    frames = _read_frames(args.current, args.frames)
    camera = _camera(frames, args.intrinsics)
    stack = np.stack([frame.depth for frame in frames])
    depth = fuse_depth(stack, min_valid=reference.params.min_valid(len(frames)))
    return depth, depth, camera, camera


def cmd_capture(args: argparse.Namespace) -> int:
    """Build a SceneModel (a station reference) from N frames and save it."""
    from robot_change.change.scene import build_scene

    mount = CameraMount.parse(args.mount) if args.mount else None
    frames = _read_frames(args.source, args.frames)
    scene = build_scene(frames, _scene_params(args), intrinsics=_camera(frames, args.intrinsics),
                        source=args.source, mount=mount, noise=_profile(args, args.source))
    scene.save(args.out)
    limit = _limit_of(scene)
    print(f"wrote {args.out}: {scene.n_frames} frame(s) fused, {len(scene.points)} points, "
          f"K = {scene.mixture.n_components}, {scene.seconds['total']:.2f} s, noise "
          f"{scene.noise.name}, smallest change seen {_cm(limit.median_m)} at the view's "
          "median depth" + ("" if mount is None else f", mount {_mount_text(mount)}")
          + ("" if scene.drift is None else f", drift {scene.drift:.2f} (still: about 1)"))
    if scene.moved_while_captured:
        print(f"warning: the view moved while its {scene.n_frames} frames were taken (drift "
              f"{scene.drift:.2f}): the reference is blurred and its noise raised by the "
              "motion; capture it again with the camera and the scene still", file=sys.stderr)
    if args.format:
        cloud_path = Path(args.out).with_suffix(f".{args.format}")
        _, frame = _write_point_files({cloud_path: (scene.points, None)}, args.format, mount)
        print(f"wrote {cloud_path}: the clean cloud, {frame} frame")
    return 0


def _limit_of(scene):
    """The smallest change a check of ``scene`` reports (robot_change.change.limits)."""
    from robot_change.change.limits import detection_limit
    from robot_change.change.params import ChangeParams

    return detection_limit(scene.depth, scene.noise, ChangeParams(), scene.params.cloud.leaf_m,
                           scene.intrinsics.fx)


def _cm(metres: float) -> str:
    return f"{metres * 100:.0f} cm" if np.isfinite(metres) else "nothing (no depth in range)"


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Measure a still camera's noise and write its profile (robot_change.tools.calibrate)."""
    from robot_change.tools.calibrate import calibrate, calibration_summary

    out = Path(args.out)
    with open_depth(args.source) as source:
        _CAMERA_MODEL[args.source] = (getattr(source, "info", None) or {}).get("name") or None
        base = _profile(args, args.source)
        profile, noise, seconds = calibrate(source, base, out, args.frames)
    summary = calibration_summary(profile, base, noise, seconds, out)
    if args.json:
        _print_json(summary)
        return 0
    print(f"wrote {out}: {profile.name} from {noise.n_frames} frames in {seconds:.1f} s; step "
          f"{noise.step_per_m * 1e3:.2f} mm/m^2, flicker {noise.flicker_valid:.2%} (valid) "
          f"{noise.flicker_step:.2%} (steps), flying pixels {noise.edge_px} px from an edge, "
          f"drift {noise.drift:.2f} (still: about 1)")
    print("depth m   sigma mm   built-in mm   pixels")
    for row in summary["bins"]:
        print(f"{row['depth_m']:7.2f} {row['sigma_mm']:10.2f} {row['builtin_sigma_mm']:13.2f} "
              f"{row['pixels']:8d}")
    return 0


def _mount_text(mount: CameraMount) -> str:
    return ",".join(f"{v:g}" for v in (*mount.xyz_m, *mount.rpy_deg))


def _detect_mount(args: argparse.Namespace, reference) -> CameraMount:
    """``--mount`` if given, else the mounting the reference was captured with, else the
    identity; a ``--mount`` that differs from the reference's is used, with a warning."""
    recorded = getattr(reference, "mount", None)
    if not args.mount:
        return recorded if recorded is not None else CameraMount()
    mount = CameraMount.parse(args.mount)
    if recorded is not None and recorded != mount:
        print(f"robot-change detect: warning: the reference was captured with the camera "
              f"mounted at {_mount_text(recorded)}; using --mount {_mount_text(mount)}",
              file=sys.stderr)
    return mount


def cmd_detect(args: argparse.Namespace) -> int:
    """Compare a reference with now: what appeared, what disappeared, where."""
    from robot_change.change import baselines
    from robot_change.change.detect import detect_changes

    started = time.perf_counter()
    stamp_ns = time.time_ns()
    if args.mcap:
        from robot_change.export.foxglove import sdk

        sdk()  # without foxglove-sdk, say so before the work
    out = _out_folder(args.out)
    reference = _reference_scene(args)
    current, current_depth, camera, told = _current_input(args, reference)
    detector = {"novelty": detect_changes, "plain": baselines.detect_plain,
                "geometric": baselines.detect_geometric, "nn": baselines.detect_nn_threshold}
    mount = _detect_mount(args, reference)
    changes = detector[args.method](reference, current, intrinsics=told)
    seconds = time.perf_counter() - started
    known = mount if args.mount or getattr(reference, "mount", None) is not None else None
    summary = changes.summary(known)
    summary.update({"reference": args.reference, "current": args.current,
                    "seconds": round(seconds, 3)})
    if out is not None:
        summary["files"], summary["points_frame"] = _write_point_files(
            {out / f"appeared.{args.format}": (changes.appeared_points, APPEARED_COLOR),
             out / f"disappeared.{args.format}": (changes.disappeared_points,
                                                   DISAPPEARED_COLOR)}, args.format, known)
        summary["files"].append(str(out / "report.json"))
        if not args.no_picture:
            from robot_change.tools.report import draw_change

            seen = "" if changes.limit is None else (
                f"; smallest change seen {_cm(changes.limit.median_m)} at the median depth")
            draw_change(reference.depth, current_depth, camera, changes, out / "report.png",
                        title=f"{args.reference} -> {args.current}\nnoise "
                        f"{reference.noise.name}{seen}")
            summary["files"].append(str(out / "report.png"))
        from hw.atomic import write_atomically

        if args.mcap:
            summary["files"].append(str(args.mcap))
        write_atomically(out / "report.json",
                         (json_text.dumps(summary, indent=2) + "\n").encode("utf-8"))
    if args.mcap:
        _write_check_mcap(args.mcap, reference, current_depth, changes, mount, summary, stamp_ns)
        if out is None:
            summary["files"] = [str(args.mcap)]
    if args.json:
        _print_json(summary)
    else:
        _print_change_summary(summary)
    return DETECT_EXIT[changes.outcome] if args.exit_code else 0


def _write_check_mcap(path: str, reference, current_depth: np.ndarray, changes,
                      mount: CameraMount, summary: dict[str, Any], stamp_ns: int) -> None:
    """``detect --mcap``: the check as one MCAP file for Foxglove (robot_change.export)."""
    from robot_change.export.foxglove import check_messages
    from robot_change.export.mcap import CheckFileWriter

    messages = check_messages(reference, current_depth, changes, mount, report=summary,
                              stamp_ns=stamp_ns)
    CheckFileWriter().write(path, messages, stamp_ns, {"outcome": changes.outcome})


def _print_change_summary(summary: dict[str, Any]) -> None:
    verdict = {"changed": "CHANGED", "no_change": "no change",
               "not_at_station": "NOT AT STATION"}[summary["outcome"]]
    print(f"{verdict}: {summary['reference']} -> {summary['current']} "
          f"(K {summary['k_reference']} / {summary['k_current']}, {summary['seconds']:.2f} s)")
    offset, reg = summary["offset_base"], summary["registration"]
    print(f"  offset from the station pose ({summary['base_frame']}): "
          + " ".join(f"{a} {v * 100:+.1f} cm"
                     for a, v in zip("xyz", offset["translation_m"], strict=False))
          + ", " + " ".join(f"{a} {v:+.2f} deg" for a, v in
                            zip(("roll", "pitch", "yaw"), offset["rpy_deg"], strict=False))
          + f"; fitness {reg['fitness']:.2f}, unobserved {summary['unobserved_fraction']:.0%}"
          + (f"; weak: {', '.join(offset['weak_directions'])}"
             if offset["weak_directions"] else ""))
    if summary["not_at_station_reason"]:
        print(f"  {summary['not_at_station_reason']}")
    for number, region in enumerate(summary["regions"], 1):
        x, y, z = region["centroid_m"]
        bx, by, bz = region["base"]["centroid_m"]
        print(f"  {region['kind']:11s} {number}: {region['n_points']:5d} points at "
              f"x {x:+.2f} y {y:+.2f} z {z:.2f} m (camera), {bx:.2f} m ahead, {by:+.2f} m "
              f"left, {bz:+.2f} m up ({summary['base_frame']}), extent "
              + " x ".join(f"{v:.2f}" for v in region["extent_m"]) + " m")
    for path in summary.get("files", []):
        print(f"wrote {path}")
