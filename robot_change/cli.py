"""``robot-change``: the command line.  The one place that builds hardware and wires it up.

Exit status: 0 success, 2 bad input (a file, URI, option or parameter the command cannot use; the
message says what to change), 78 a configuration error (EX_CONFIG: systemd does not restart the
service for it), 1 an internal error.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

import robot_change
from hw.atomic import STALE_AFTER_S, remove_temp_files
from hw.depth import DepthFrame, Intrinsics, open_depth
from hw.errors import HwError
from hw.pointfile import POINT_FORMATS, write_points
from robot_change import validate
from robot_change.change.mount import CameraMount
from robot_change.errors import ConfigError, InputError, RobotChangeError
from robot_change.noise.profile import AUTO_PROFILE, BUILTIN, DEFAULT_PROFILE

#: Exit status for a configuration error (sysexits' EX_CONFIG); the unit file names it in
#: RestartPreventExitStatus.  Kept equal to robot_change.service.config.EXIT_CONFIG (a test checks).
EXIT_CONFIG = 78

log = logging.getLogger("robot_change.cli")  # also when run as __main__ (python -m)


def _fixtures_folder() -> Path:
    """The bundled fixtures: the ``sim_fixtures`` package (installed with the demo's and the
    bench's recordings as package data, or the checkout's), found without importing it."""
    spec = importlib.util.find_spec("sim_fixtures")
    if spec is not None and spec.origin:
        return Path(spec.origin).resolve().parent
    return Path(__file__).resolve().parents[1] / "sim_fixtures"


#: The bundled fixtures (the recordings ``demo`` and ``bench`` use).
SIM_FIXTURES = _fixtures_folder()
#: The VGA frame of a furnished room (Kinect noise model) used by ``demo`` and ``bench``.
DEMO_FRAME = SIM_FIXTURES / "frames" / "room_vga.png"
#: The bundled scene ``bench`` times change detection on (a box appears in an office).
DETECT_SCENE = "office_box_added"


# ---------------------------------------------------------------------------------------------
# helpers


def _bundled(path: Path) -> str:
    if not path.exists():
        raise InputError(
            f"the bundled fixture {path} is missing (it ships with robot-change: reinstall "
            "it), or pass --source URI to use your own depth"
        )
    return str(path)


def _read_depth(uri: str, frames: int, intrinsics: str | None) -> tuple[np.ndarray, Intrinsics, int]:
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

    overrides = {}
    if getattr(args, "leaf", None) is not None:
        overrides["leaf_m"] = args.leaf
    return CloudParams(**overrides)


def _describe_plane(plane) -> dict[str, Any] | None:
    """The removed plane as plain numbers (None when none was found)."""
    if not plane.found:
        return None
    return {
        "normal": [round(float(v), 4) for v in plane.normal],
        "distance_m": round(float(plane.offset), 4),
        "inliers": int(plane.n_inliers),
    }


def _print_json(payload: dict[str, Any]) -> None:
    print(json.dumps(payload, indent=None, sort_keys=False))


#: Colours of the changed points in .pcd / .ply files (r, g, b).
APPEARED_COLOR, DISAPPEARED_COLOR = (0, 200, 0), (220, 0, 0)


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


# ---------------------------------------------------------------------------------------------
# commands


def cmd_cloud(args: argparse.Namespace) -> int:
    """Depth -> clean cloud: print a summary, optionally save the points and a picture."""
    from robot_change.cloud.chain import clean_cloud

    started = time.perf_counter()
    mount = CameraMount.parse(args.mount) if args.mount else None
    depth, camera, n_frames = _read_depth(args.source, args.frames, args.intrinsics)
    params = _cloud_params(args)
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
    out_dir = Path(args.out) if args.out else None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
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
    print("time        " + ", ".join(f"{key[:-3]} {value:.2f} ms" for key, value in timings.items()))
    for path in summary.get("files", []):
        print(f"wrote       {path}")


def cmd_demo(args: argparse.Namespace) -> int:
    """The README's main job on a bundled recording: the real daemon in a subprocess, the
    simulated base on a pty pair; capture a reference, the scene changes, check, PAUSE and
    CHANGE_REPORT, and report.png of what changed (robot_change.tools.demo)."""
    from robot_change.tools.demo import run_demo

    return run_demo(Path(args.out), SIM_FIXTURES)


def cmd_run(args: argparse.Namespace) -> int:
    """The daemon (robot_change.service.core): camera, serial line and store from the configuration,
    until SIGTERM; SIGHUP reloads the configuration.  Exit 78 for a configuration error, 70
    after a stall (robot_change.service.daemon)."""
    from hw.serial_port import ReopeningPort
    from robot_change.service import systemd
    from robot_change.service.core import Service, ServiceOptions
    from robot_change.service.daemon import run_service, stall_bound
    from robot_change.service.params import load_checked_config
    from robot_change.service.store import ReferenceStore

    config = load_checked_config(args.config)
    _setup_logging(args.log_level or config.service.log_level)

    def make_camera(cfg: Any) -> Any:  # the one place a depth source is built
        return lambda: open_depth(cfg.camera.source)

    port = ReopeningPort(config.serial.port, config.serial.baud, timeout=0.01)
    service = None
    try:
        store = ReferenceStore(config.store.references, max_stations=config.store.max_stations,
                               min_free_mb=config.store.min_free_mb)
        options = ServiceOptions(report_dir=Path(config.store.state_dir) / "reports",
                                 stall_after_s=stall_bound(systemd.watchdog_interval()))
        service = Service(config, make_camera(config), port, store, options)
        status = run_service(service, load=lambda: load_checked_config(args.config, reload=True),
                             make_camera=make_camera)
    finally:
        port.close()
    if service is not None and service.stuck:
        # an interpreter exit would wait for them (a hung kernel, a compile in progress)
        logging.getLogger(__name__).warning("exiting with %s still running",
                                            ", ".join(service.stuck))
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    return status


def cmd_warm_up(args: argparse.Namespace) -> int:
    """Compile the numba kernels into the cache (NUMBA_CACHE_DIR, else beside the package), so
    that the next start of the daemon or of a command loads them instead."""
    from robot_change.service.warmup import warm_up

    seconds = warm_up()
    where = os.environ.get("NUMBA_CACHE_DIR") or "the package's __pycache__ folders"
    print(f"kernels ready in {seconds:.1f} s (cache: {where})")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    """Speed of the pipeline on one bundled VGA frame (medians after warm-up, milliseconds)."""
    from robot_change.tools.benchmark import (
        bench_capture,
        bench_detect,
        bench_emd,
        bench_preprocess,
        benchmark_em,
        machine_info,
    )

    source = args.source or _bundled(DEMO_FRAME)
    depth, camera, _ = _read_depth(source, 1, None)
    params = _cloud_params(args)
    result: dict[str, Any] = {"frame": source, "runs": args.runs}
    result.update(bench_preprocess(depth, camera, params, runs=args.runs))
    # the mixture and change detection on a bundled room scene: its reference (3 fused frames,
    # a room-sized cloud of ~20k points) and one current frame
    from hw.oni import read_oni_frames
    from robot_change.change.scene import build_scene

    scene_dir = SIM_FIXTURES / "scenes" / DETECT_SCENE
    reference_frames = read_oni_frames(_bundled(scene_dir / "reference.oni"))
    current = read_oni_frames(_bundled(scene_dir / "current.oni"))[0]
    result.update(bench_capture(reference_frames, runs=max(3, args.runs // 3)))
    reference = build_scene(reference_frames)
    mixture = benchmark_em(reference.points, runs=max(3, args.runs // 4),
                           leaf=reference.params.cloud.leaf_m)
    result.update({
        "scene": DETECT_SCENE,
        "em_iter_ms": round(mixture["em_iter_ms"], 3),
        "em_iter_points": mixture["iter_points"],
        "fit_ms": round(mixture["fit_ms"], 2),
        "fit_k": mixture["fit_k"],
        "fit_points": mixture["n_points"],
    })
    result.update(bench_detect(reference, current.depth, current.intrinsics,
                               runs=max(5, args.runs // 3)))
    emd_figures = bench_emd(runs=max(20, args.runs * 4), n_scenes=3)
    result["emd_10x10_us"] = emd_figures["emd_10x10_us"]
    result["greedy_both_ways_k30_ms"] = emd_figures["greedy_both_ways_k30_ms"]
    result["machine"] = machine_info()
    if args.json:
        _print_json(result)
    else:
        width = max(len(key) for key in result) + 2
        for key, value in result.items():
            print(f"{key:{width}s}{value}")
    return 0


def _is_scene_file(target: str) -> bool:
    """A saved SceneModel (``*.npz``) rather than a depth URI."""
    return target.lower().endswith(".npz")


def _read_frames(uri: str, frames: int) -> list[DepthFrame]:
    """Up to ``frames`` frames from a depth URI (fewer when a recording is shorter).  The
    camera's model, when the source names one, is kept in ``_CAMERA_MODEL[uri]`` (the
    ``auto`` noise profile)."""
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
        log.warning("%s ended after %d of the %d frames asked for (--frames); using %d", uri,
                    len(read), frames, len(read))
    return read


def _scene_params(args: argparse.Namespace):
    from robot_change.change.scene import SceneParams

    return SceneParams(cloud=_cloud_params(args))


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
    """The current epoch: a saved SceneModel, or the fused depth of a URI's frames and the
    intrinsics to read it with."""
    from robot_change.change.scene import SceneModel
    from robot_change.cloud.fusion import fuse_depth

    if _is_scene_file(args.current):
        scene = SceneModel.load(args.current)
        return scene, scene.depth, scene.intrinsics
    frames = _read_frames(args.current, args.frames)
    camera = _camera(frames, args.intrinsics)
    stack = np.stack([frame.depth for frame in frames])
    depth = fuse_depth(stack, min_valid=reference.params.min_valid(len(frames)))
    return depth, depth, camera


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
          "median depth" + ("" if mount is None else f", mount {_mount_text(mount)}"))
    if args.format:
        cloud_path = Path(args.out).with_suffix(f".{args.format}")
        _, frame = _write_point_files({cloud_path: (scene.points, None)}, args.format, mount)
        print(f"wrote {cloud_path}: the clean cloud, {frame.replace('_', ' ')} frame")
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
          f"{noise.flicker_step:.2%} (steps), flying pixels {noise.edge_px} px from an edge")
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
    reference = _reference_scene(args)
    current, current_depth, camera = _current_input(args, reference)
    detector = {"novelty": detect_changes, "plain": baselines.detect_plain,
                "geometric": baselines.detect_geometric, "nn": baselines.detect_nn_threshold}
    mount = _detect_mount(args, reference)
    changes = detector[args.method](reference, current, intrinsics=camera)
    seconds = time.perf_counter() - started
    summary = changes.summary(mount)
    summary.update({
        "reference": args.reference, "current": args.current, "seconds": round(seconds, 3),
    })
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        known = mount if args.mount or getattr(reference, "mount", None) is not None else None
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
                         (json.dumps(summary, indent=2) + "\n").encode("utf-8"))
    if args.mcap:
        _write_check_mcap(args.mcap, reference, current_depth, changes, mount, summary, stamp_ns)
        if not args.out:
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
    print("  offset from the station pose (base_link): "
          + " ".join(f"{a} {v * 100:+.1f} cm" for a, v in zip("xyz", offset["translation_m"]))
          + ", " + " ".join(f"{a} {v:+.2f} deg" for a, v in
                            zip(("roll", "pitch", "yaw"), offset["rpy_deg"]))
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
              f"left, {bz:+.2f} m up (base), extent "
              + " x ".join(f"{v:.2f}" for v in region["extent_m"]) + " m")
    for path in summary.get("files", []):
        print(f"wrote {path}")


def cmd_record(args: argparse.Namespace) -> int:
    """Record any depth source (a live camera, images, a recording, a bag) to an .oni file, a
    ROS 2 bag folder (MCAP storage) or a RealSense recording (.db3, by librealsense)."""
    from hw.record import record

    suffix = Path(args.out).suffix.lower()
    out_format = args.format or {".oni": "oni", ".db3": "realsense"}.get(suffix, "rosbag2")
    codecs = {"oni": ("16zt", "16z", "none"), "realsense": ("png", "none")}.get(out_format, ())
    if args.codec is not None and args.codec not in codecs:
        raise InputError(f"--codec {args.codec} is not for a {out_format} recording: "
                         + (f"choose {' or '.join(codecs)}" if codecs else "a ROS 2 bag is "
                            "written with zstd-compressed MCAP chunks (lossless)"))
    shown = [0.0]

    def progress(frames: int, seconds: float, size: int) -> None:
        if time.monotonic() - shown[0] >= 0.25:  # a line on a terminal, 4 times a second
            shown[0] = time.monotonic()
            print(f"\rrecording: {frames} frames, {seconds:.1f} s, {size / 1e6:.1f} MB "
                  "(Ctrl-C stops and keeps them)", end="", file=sys.stderr, flush=True)

    with open_depth(args.source) as source:
        written = record(source, args.out, frames=args.frames,
                         codec=args.codec or (codecs[0] if codecs else "16zt"),
                         progress=progress if sys.stderr.isatty() else None, format=out_format)
    if sys.stderr.isatty():
        print(file=sys.stderr)
    out = Path(args.out)
    size = sum(item.stat().st_size for item in out.iterdir()) if out.is_dir() else \
        out.stat().st_size
    what = {"oni": "", "rosbag2": " (a ROS 2 bag: ros2 bag info / play it)",
            "realsense": " (a RealSense recording: play it with realsense:FILE or the "
                         "RealSense Viewer)"}[out_format]
    print(f"wrote {written} frame(s), {size / 1e6:.1f} MB, to {args.out}{what}")
    return 0


def cmd_list_devices(args: argparse.Namespace) -> int:
    """The OpenNI2 and RealSense cameras connected now, each with its URI."""
    import importlib

    from hw.errors import BackendUnavailable

    devices, missing = [], {}
    for backend, module in (("openni2", "hw.openni2"), ("realsense", "hw.realsense")):
        try:
            found = importlib.import_module(module).list_devices()
        except (ImportError, BackendUnavailable) as exc:
            missing[backend] = str(exc)
            continue
        for device in found:
            serial = device.get("serial") or ""
            uri = f"realsense://{serial}" if backend == "realsense" else \
                f"openni2://{serial or device['uri']}"
            devices.append({"backend": backend, "source": uri, **device})
    if args.json:
        _print_json({"devices": devices, **({"unavailable": missing} if missing else {})})
        return 0
    for device in devices:
        what = " ".join(str(device.get(key) or "") for key in ("vendor", "name")).strip()
        firmware = f"  firmware {device['firmware']}" if device.get("firmware") else ""
        print(f"{device['source']}  {what}{firmware}")
    if not devices:
        print("no OpenNI2 camera found (is it plugged in? a Kinect v1 needs libfreenect's "
              "OpenNI2 driver; see the README)")
        print("no RealSense camera found" if "realsense" not in missing else
              "RealSense cameras are not looked for: install the realsense extra "
              "(pip install pyrealsense2)")
    return 0


def cmd_check_config(args: argparse.Namespace) -> int:
    """Read and check a configuration file; print the effective settings."""
    from robot_change.service.params import load_checked_config

    config = load_checked_config(args.file)
    if args.json:
        _print_json(config.as_dict())
    else:
        print(f"# {args.file}: OK; the effective settings (defaults included):")
        print(config.as_toml(), end="")
    return 0


def cmd_base_sim(args: argparse.Namespace) -> int:
    """A simulated base controller on a serial port: interactive, or driven by a script."""
    from robot_change.tools.basesim import run_base_sim

    return run_base_sim(args.port, args.script, baudrate=args.baud, verbose=args.verbose,
                        proto_max=args.protocol)


def cmd_fleet_tail(args: argparse.Namespace) -> int:
    """The fleet's changes and status as they come (robot_change.tools.fleettail)."""
    from robot_change.fleet.connection import BrokerSettings
    from robot_change.tools.fleettail import run_fleet_tail

    validate.broker_url("fleet-tail", "--broker", args.broker)
    settings = BrokerSettings(args.broker, args.ca_file, args.cert_file, args.key_file,
                              args.username, args.password_file)
    return run_fleet_tail(settings, prefix=args.prefix, robot=args.robot, checks=args.checks,
                          as_json=args.json, session=args.session, count=args.count,
                          seconds=args.seconds)


def cmd_link_bench(args: argparse.Namespace) -> int:
    """PAUSE round trips, reports, STATUS or a flood over a pty pair through a noisy relay."""
    from robot_change.tools.linkbench import run_link_bench

    result = run_link_bench(args.corrupt, args.count, args.baud, args.json, seed=args.seed,
                            mode=args.mode, noise=args.noise, proto=args.proto,
                            regions=args.regions)
    ok = {"pause": result.get("delivered"), "report": result.get("reports_complete"),
          "status": result.get("answered")}.get(args.mode)
    if args.mode == "flood":
        return 0 if result["answers_dropped"] == 0 else 1
    return 0 if ok == result["sent"] else 1


# ---------------------------------------------------------------------------------------------
# parser


#: ``detect --exit-code``: the exit status of each outcome (2 stays "an error").
DETECT_EXIT = {"no_change": 0, "changed": 1, "not_at_station": 3}

#: Logging as every command sets it up (``--log-level``, ``-v``, ``-q``); the daemon's default
#: is its configuration's ``[service] log_level``, a one-shot command's "warning".
LOG_LEVELS = ("debug", "info", "warning", "error")


def _setup_logging(level: str) -> None:
    """Log lines to stderr, with a timestamp unless the journal (which stamps them) reads it;
    ``level`` for robot_change and hw, warnings and worse from the libraries underneath."""
    from robot_change.service.daemon import (
        set_log_level,  # (cli imports lazily: a quick --help)
    )

    stamp = "" if os.environ.get("JOURNAL_STREAM") else "%(asctime)s "
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, force=True,
                        format=stamp + "%(levelname)s %(name)s: %(message)s")
    set_log_level(level)


def _count(text: str) -> int:
    """An argparse type: a whole number >= 1 (frames, runs, round trips)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value}: must be at least 1")
    return value


#: ``--format`` of cloud, capture and detect: hw.pointfile.POINT_FORMATS.
FORMAT_HELP = ("npy (default: (M,3) float32, camera optical frame), pcd (binary) or ply; "
               ".pcd / .ply are in base_link when the camera's --mount is known, else in the "
               "camera optical frame, and say which (PCD VIEWPOINT, PLY comment)")
PROFILE_HELP = (f"the camera's noise: a built-in profile ({', '.join(BUILTIN)}), "
                f"{AUTO_PROFILE} (default: the camera model's own, as its driver names it; "
                f"{DEFAULT_PROFILE} for recordings, images and bags that name none) or a file "
                "written by `robot-change calibrate`")
MOUNT_HELP = ("the camera on the base: x,y,z,roll,pitch,yaw of its body frame (x forward, y "
              "left, z up) in base_link, metres and degrees; .pcd / .ply points are then "
              "written in base_link")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="robot-change",
        description="Scene change detection for robots with a depth camera.",
    )
    parser.add_argument("--version", action="version",
                        version=f"robot-change {robot_change.__version__}")
    # every command takes the logging options (base-sim keeps -v for its own verbose output)
    logs = argparse.ArgumentParser(add_help=False)
    logs.add_argument("--log-level", choices=LOG_LEVELS,
                      help="log verbosity (default: warning; run: the configuration's)")
    logs.add_argument("-q", "--quiet", dest="log_level", action="store_const", const="error",
                      help="errors only")
    verbose = argparse.ArgumentParser(add_help=False, parents=[logs])
    verbose.add_argument("-v", "--verbose", dest="log_level", action="store_const", const="debug",
                         help="debug logging")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    class _Commands:
        """add_parser with the logging options on every command."""

        @staticmethod
        def add_parser(name: str, **kwargs: Any) -> argparse.ArgumentParser:
            parents = [logs] if name == "base-sim" else [verbose]
            return subparsers.add_parser(name, parents=parents, **kwargs)

    commands = _Commands()

    cloud = commands.add_parser("cloud", help="depth -> clean point cloud, with a summary and a picture")
    cloud.add_argument("--source", required=True, help="depth URI: openni2://, FILE.oni, images:DIR, FILE.png")
    cloud.add_argument("--frames", type=_count, default=1, help="frames to fuse by per-pixel median (default 1)")
    cloud.add_argument("--intrinsics", help="fx,fy,cx,cy in pixels (default: the source's, else OpenNI's VGA)")
    cloud.add_argument("--leaf", type=float, help="voxel size in metres (default from CloudParams)")
    cloud.add_argument("--out", help="folder for cloud.npy ((M,3) float32, metres; or .pcd / .ply, "
                       "--format) and cloud.png")
    cloud.add_argument("--format", choices=POINT_FORMATS, default="npy", help=FORMAT_HELP)
    cloud.add_argument("--mount", help=MOUNT_HELP)
    cloud.add_argument("--no-picture", action="store_true", help="with --out: skip cloud.png")
    cloud.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    cloud.set_defaults(func=cmd_cloud)

    demo = commands.add_parser("demo", help="the daemon and a simulated base on a bundled "
                               "recording: capture, change, check, PAUSE + report.png")
    demo.add_argument("--out", default="demo-out", help="output folder (default demo-out)")
    demo.set_defaults(func=cmd_demo)

    run = commands.add_parser("run", help="the daemon (systemd Type=notify; SIGHUP reloads, "
                              "SIGTERM stops; exit 78 for a configuration error)")
    run.add_argument("--config", required=True, metavar="FILE",
                     help="TOML file, e.g. /etc/robot-change/robot-change.toml")
    run.set_defaults(func=cmd_run)

    warm = commands.add_parser("warm-up", help="compile the numba kernels into the cache now "
                               "(a cold first start otherwise spends a minute or more on it)")
    warm.set_defaults(func=cmd_warm_up)

    bench = commands.add_parser("bench", help="speed of each stage on a bundled VGA frame")
    bench.add_argument("--json", action="store_true", help="print one JSON object")
    bench.add_argument("--runs", type=_count, default=30, help="timed runs after warm-up (default 30)")
    bench.add_argument("--source", help="depth URI to benchmark instead of the bundled frame")
    bench.set_defaults(func=cmd_bench)

    capture = commands.add_parser("capture", help="build a station reference (SceneModel) from "
                                  "N frames and save it")
    capture.add_argument("--source", required=True, help="depth URI (camera, .oni, images)")
    capture.add_argument("--out", required=True, help="the file to write, e.g. kitchen.scene.npz")
    capture.add_argument("--frames", type=_count, default=5, help="frames to fuse (default 5)")
    capture.add_argument("--intrinsics", help="fx,fy,cx,cy in pixels (default: the source's)")
    capture.add_argument("--leaf", type=float, help="voxel size in metres (default 0.03)")
    capture.add_argument("--mount", help="the camera on the base, recorded with the reference: "
                         "x,y,z,roll,pitch,yaw of its body frame (x forward, y left, z up) in "
                         "base_link, metres and degrees; detect uses it unless given --mount")
    capture.add_argument("--format", choices=POINT_FORMATS,
                         help="also write the clean cloud beside --out (REF.scene.pcd, .ply or "
                         ".npy); " + FORMAT_HELP.split("; ", 1)[1])
    capture.add_argument("--profile", default=AUTO_PROFILE, help=PROFILE_HELP)
    capture.set_defaults(func=cmd_capture)

    calibrate = commands.add_parser("calibrate", help="measure a still camera's noise and "
                                    "write its profile ([camera] profile_file)")
    calibrate.add_argument("--source", required=True, help="depth URI of the camera (or a "
                           "recording of a still view)")
    calibrate.add_argument("--out", required=True, help="the profile file to write (JSON)")
    calibrate.add_argument("--frames", type=_count, default=30,
                           help="frames to read (default 30: 1 s at 30 fps)")
    calibrate.add_argument("--profile", default=AUTO_PROFILE,
                           help="the built-in profile of this kind of camera (its principle, "
                           "range and the shape of its noise beyond the measured depths; "
                           f"default {AUTO_PROFILE}: the camera model's own, {DEFAULT_PROFILE} "
                           "for a source that names none)")
    calibrate.add_argument("--json", action="store_true", help="print one JSON object")
    calibrate.set_defaults(func=cmd_calibrate)

    detect = commands.add_parser("detect", help="compare a reference with now: what appeared, "
                                 "what disappeared, where")
    detect.add_argument("--reference", required=True,
                        help="a saved scene (*.npz from capture) or a depth URI")
    detect.add_argument("--current", required=True,
                        help="a saved scene (*.npz) or a depth URI (.oni, images, camera)")
    detect.add_argument("--frames", type=_count, default=5,
                        help="frames to fuse from a depth URI (default 5, fewer if it is shorter)")
    detect.add_argument("--intrinsics", help="fx,fy,cx,cy in pixels (default: the source's, "
                        "else OpenNI's VGA default)")
    detect.add_argument("--leaf", type=float,
                        help="voxel size in metres for a reference built from a URI")
    detect.add_argument("--profile", default=AUTO_PROFILE,
                        help=PROFILE_HELP + " (a reference from a file keeps its own)")
    detect.add_argument("--method", choices=("novelty", "plain", "geometric", "nn"),
                        default="novelty", help="ours (default), the paper's plain method, or a "
                        "baseline without a mixture")
    detect.add_argument("--out", help="folder for appeared.npy, disappeared.npy ((M,3) float32, "
                        "camera frame, m; or .pcd / .ply, --format), report.json and report.png")
    detect.add_argument("--format", choices=POINT_FORMATS, default="npy",
                        help=FORMAT_HELP + "; appeared points green, disappeared red")
    detect.add_argument("--no-picture", action="store_true", help="with --out: skip report.png")
    detect.add_argument("--mcap", metavar="FILE",
                        help="write the check as one MCAP file for Foxglove: depth images, "
                        "clean clouds, mixtures, changed points, region boxes, frames, the "
                        "report (docs/ros.md; the viz extra)")
    detect.add_argument("--mount", help="the camera on the base: x,y,z,roll,pitch,yaw of its "
                        "body frame (x forward, y left, z up) in base_link, metres and degrees "
                        "(default: the mounting the reference was captured with, else "
                        "0,0,0,0,0,0: at the base origin, looking ahead); base-frame "
                        "positions and the robot's offset in report.json use it")
    detect.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    detect.add_argument("--exit-code", action="store_true",
                        help="exit 1 when something changed, 3 when not at the station, 0 when "
                             "nothing changed (2 stays an error), like git diff --exit-code")
    detect.set_defaults(func=cmd_detect)

    record = commands.add_parser("record", help="record a depth source to an .oni file, a ROS 2 "
                                 "bag (MCAP) or a RealSense recording (.db3)")
    record.add_argument("--source", required=True, help="depth URI (camera, .oni, images, bag)")
    record.add_argument("--out", required=True, help="FILE.oni, FILE.db3 (a RealSense "
                        "recording), or the folder of a ROS 2 bag (as ros2 bag record -o NAME: "
                        "NAME/NAME.mcap and metadata.yaml)")
    record.add_argument("--format", choices=("oni", "rosbag2", "realsense"),
                        help="oni; rosbag2: sensor_msgs/Image 16UC1 on /camera/depth/image_raw "
                        "and CameraInfo beside it, stamped with the frames' timestamps; "
                        "realsense: written by librealsense's own recorder (needs the realsense "
                        "extra), plays in librealsense and the RealSense Viewer (default: by "
                        "--out's ending, .oni, .db3, else rosbag2)")
    record.add_argument("--frames", type=_count, help="stop after N frames (default: to the end, or Ctrl-C)")
    record.add_argument("--codec", choices=("16zt", "16z", "png", "none"),
                        help=".oni: 16zt: lossless, ~4x smaller than raw on Kinect depth "
                        "(default); 16z: lossless, for unquantised depth; none: raw uint16. "
                        ".db3: png (librealsense's compressedDepth, default) or none (raw: "
                        "about 5x larger, played with a quarter of the CPU)")
    record.set_defaults(func=cmd_record)

    devices = commands.add_parser("list-devices", help="list the OpenNI2 and RealSense cameras "
                                  "connected now, with the --source of each")
    devices.add_argument("--json", action="store_true", help="print one JSON object")
    devices.set_defaults(func=cmd_list_devices)

    check = commands.add_parser("check-config", help="read and check a configuration file "
                                "(exit 78 when it is wrong)")
    check.add_argument("file", metavar="FILE",
                       help="TOML file, e.g. /etc/robot-change/robot-change.toml")
    check.add_argument("--json", action="store_true",
                       help="print the effective configuration as one JSON object")
    check.set_defaults(func=cmd_check_config)

    base_sim = commands.add_parser("base-sim", help="a simulated base controller on a serial port "
                                   "(interactive, or --script)")
    base_sim.add_argument("--port", required=True,
                          help="serial port: /dev/ttyUSB0, a pty path, loop://, socket://HOST:PORT")
    base_sim.add_argument("--script", help="commands from FILE (wait / expect / expect-none lines "
                          "too); exit 1 when one fails")
    base_sim.add_argument("--baud", type=int, default=115200, help="baud rate (default 115200)")
    base_sim.add_argument("--protocol", type=int, choices=(1, 2, 3, 4), default=4,
                          help="the highest protocol version the simulated base speaks "
                          "(1, 2: an older base firmware, whole frames; 3: PARTs; default 4: "
                          "CAPTURED tells what the station can see)")
    base_sim.add_argument("-v", "--verbose", action="store_true",
                          help="print every heartbeat and ack")
    base_sim.set_defaults(func=cmd_base_sim)

    tail = commands.add_parser("fleet-tail", help="print the fleet's changes and status from "
                               "an MQTT broker as they come")
    tail.add_argument("--broker", required=True, metavar="URL",
                      help="mqtt://HOST[:PORT] or mqtts://HOST[:PORT] (TLS)")
    tail.add_argument("--prefix", default="robot-change",
                      help="the robots' fleet.topic_prefix (default robot-change)")
    tail.add_argument("--robot", default="+", help="one robot id (default: every robot)")
    tail.add_argument("--checks", action="store_true",
                      help="every check too, not only the changes")
    tail.add_argument("--json", action="store_true", help="one JSON object a line")
    tail.add_argument("--ca-file", help="mqtts: CA certificates (PEM) of the broker's")
    tail.add_argument("--cert-file", help="mqtts: a client certificate (PEM)")
    tail.add_argument("--key-file", help="mqtts: the client certificate's key (PEM)")
    tail.add_argument("--username", help="user name at the broker")
    tail.add_argument("--password-file", help="a file holding the password alone")
    tail.add_argument("--session", metavar="NAME", help="a persistent session: the broker "
                      "keeps what comes while fleet-tail is away (same NAME next time)")
    tail.add_argument("--count", type=_count, help="exit after N messages")
    tail.add_argument("--seconds", type=float, help="exit after S seconds")
    tail.set_defaults(func=cmd_fleet_tail)

    link_bench = commands.add_parser("link-bench", help="PAUSE round trips, change reports, "
                                     "STATUS or a flood over a pty pair through a noisy, "
                                     "baud-paced relay")
    link_bench.add_argument("--mode", choices=("pause", "report", "status", "flood"),
                            default="pause", help="what to measure (default pause): report = "
                            "PAUSE + CHECK_RESULT + CHANGE_REPORT then RESUME; flood = --count "
                            "STATUS_QUERYs at once")
    link_bench.add_argument("--noise", choices=("mixed", "flip"), default="mixed",
                            help="mixed: bit flips, drops and insertions in equal shares "
                            "(default); flip: bit flips only")
    link_bench.add_argument("--proto", type=int, choices=(1, 2, 3, 4), default=4,
                            help="highest protocol version both ends offer (2: whole frames, "
                            "as before version 3; default 4)")
    link_bench.add_argument("--regions", type=int, default=3,
                            help="regions per change report in --mode report (default 3)")
    link_bench.add_argument("--corrupt", type=float, default=0.1,
                            help="probability that a byte is corrupted (default 0.1)")
    link_bench.add_argument("--count", type=_count, default=200, help="round trips (default 200)")
    link_bench.add_argument("--baud", type=int, default=115200,
                            help="line speed the relay paces (default 115200)")
    link_bench.add_argument("--seed", type=int, help="random seed of the noise")
    link_bench.add_argument("--json", action="store_true", help="print one JSON object")
    link_bench.set_defaults(func=cmd_link_bench)
    return parser


def _clear_dead_writes(out: str) -> None:
    """Remove the temp files an earlier, killed writer of ``out`` left (those of ``out``
    beside it; for a folder, the ones in it too), sparing any a live writer still updates."""
    path = Path(out)
    remove_temp_files(path.parent, path.name, STALE_AFTER_S)
    if path.is_dir():
        remove_temp_files(path, older_than_s=STALE_AFTER_S)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command != "run":  # the daemon sets these up once its configuration is read
        _setup_logging(args.log_level or "warning")
        # a SIGTERM is a Ctrl-C: a recording keeps its frames, any other write under way
        # discards its temp file
        signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        if isinstance(getattr(args, "out", None), str):
            _clear_dead_writes(args.out)
        return int(args.func(args) or 0)
    except ConfigError as exc:
        # its own exit status, which systemd does not restart (RestartPreventExitStatus)
        print(f"robot-change {args.command}: configuration error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    except (HwError, RobotChangeError) as exc:
        print(f"robot-change {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # e.g. piped into head: the reader has gone, nothing to report
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:  # a path the user gave: a missing folder, not a folder, no access
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"robot-change {args.command}: error: {where}{exc.strerror or exc}",
              file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
