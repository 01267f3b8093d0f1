"""``robot-change``: the command line.  The one place that builds hardware and wires it up.

Exit status: 0 success, 2 bad input (a file, URI, option or parameter the command cannot use; the
message says what to change), 78 a configuration error (EX_CONFIG: systemd does not restart the
service for it), 1 an internal error.

The commands themselves live in robot_change.commands (scene, recording, service, tools); this
module parses the command line, runs one and turns its errors into exit statuses.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
from pathlib import Path
from typing import Any

import robot_change
from hw.atomic import STALE_AFTER_S, remove_temp_files
from hw.depth import open_depth
from hw.errors import HwError
from hw.pointfile import POINT_FORMATS
from robot_change.commands.common import DEMO_FRAME, DETECT_SCENE, SIM_FIXTURES, DefaultFrames
from robot_change.commands.recording import cmd_list_devices, cmd_record
from robot_change.commands.scene import (
    APPEARED_COLOR,
    DETECT_EXIT,
    DISAPPEARED_COLOR,
    cmd_calibrate,
    cmd_capture,
    cmd_cloud,
    cmd_detect,
)
from robot_change.commands.service import cmd_check_config, cmd_demo, cmd_warm_up
from robot_change.commands.tools import cmd_base_sim, cmd_bench, cmd_fleet_tail, cmd_link_bench
from robot_change.errors import ConfigError, RobotChangeError
from robot_change.noise.profile import AUTO_PROFILE, BUILTIN, DEFAULT_PROFILE

#: What the command line offers as importable names (the cmd_* and constants re-exported from
#: robot_change.commands, where they live).
__all__ = [
    "APPEARED_COLOR", "DEMO_FRAME", "DETECT_EXIT", "DETECT_SCENE", "DISAPPEARED_COLOR",
    "EXIT_CONFIG", "FORMAT_HELP", "LOG_LEVELS", "MOUNT_HELP", "PROFILE_HELP", "SIM_FIXTURES",
    "build_parser", "cmd_base_sim", "cmd_bench", "cmd_calibrate", "cmd_capture",
    "cmd_check_config", "cmd_cloud", "cmd_demo", "cmd_detect", "cmd_fleet_tail",
    "cmd_link_bench", "cmd_list_devices", "cmd_record", "cmd_run", "cmd_warm_up", "main",
]

#: Exit status for a configuration error (sysexits' EX_CONFIG); the unit file names it in
#: RestartPreventExitStatus.  Kept equal to robot_change.service.config.EXIT_CONFIG (a test checks).
EXIT_CONFIG = 78


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


# ---------------------------------------------------------------------------------------------
# parser


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

    cloud = commands.add_parser("cloud", help="depth -> clean point cloud, with a summary and a "
                                "picture")
    cloud.add_argument("--source", required=True,
                       help="depth URI: openni2://, FILE.oni, images:DIR, FILE.png")
    cloud.add_argument("--frames", type=_count, default=DefaultFrames(1),
                       help="frames to fuse by per-pixel median (default 1)")
    cloud.add_argument("--intrinsics",
                       help="fx,fy,cx,cy in pixels (default: the source's, else OpenNI's VGA)")
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
                               "(a cold first start otherwise spends about half a minute on it)")
    warm.set_defaults(func=cmd_warm_up)

    bench = commands.add_parser("bench", help="speed of each stage on a bundled VGA frame")
    bench.add_argument("--json", action="store_true", help="print one JSON object")
    bench.add_argument("--runs", type=_count, default=30,
                       help="timed runs after warm-up (default 30)")
    bench.add_argument("--source", help="depth URI to benchmark instead of the bundled frame")
    bench.set_defaults(func=cmd_bench)

    capture = commands.add_parser("capture", help="build a station reference (SceneModel) from "
                                  "N frames and save it")
    capture.add_argument("--source", required=True, help="depth URI (camera, .oni, images)")
    capture.add_argument("--out", required=True, help="the file to write, e.g. kitchen.scene.npz")
    capture.add_argument("--frames", type=_count, default=DefaultFrames(5),
                         help="frames to fuse (default 5)")
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
    detect.add_argument("--frames", type=_count, default=DefaultFrames(5),
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
    record.add_argument("--frames", type=_count,
                        help="stop after N frames (default: to the end, or Ctrl-C)")
    record.add_argument("--codec", choices=("16zt", "16z", "png", "none"),
                        help=".oni: 16zt: lossless, ~4x smaller than raw on Kinect depth "
                        "(default); 16z: lossless, for unquantised depth; none: raw uint16. "
                        ".db3: png (librealsense's compressedDepth, default) or none (raw: "
                        "about 5x larger, played with 0.4 of the CPU)")
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
    base_sim.add_argument("--protocol", type=int, choices=(1, 2, 3, 4, 5), default=5,
                          help="the highest protocol version the simulated base speaks "
                          "(1, 2: an older base firmware, whole frames; 3: the module's "
                          "messages in PARTs; 4: CAPTURED tells what the station can see; "
                          "default 5: the base's commands in PARTs too)")
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
    link_bench.add_argument("--mode", choices=("pause", "report", "check", "restart", "idle",
                                               "status", "flood"),
                            default="pause", help="what to measure (default pause): report = "
                            "PAUSE + CHECK_RESULT + CHANGE_REPORT then RESUME; check = the "
                            "base's CHECK, then that answer; restart = the module restarts, "
                            "the base must see its new boot; idle = --count seconds of "
                            "heartbeats alone; flood = --count STATUS_QUERYs at once")
    link_bench.add_argument("--noise", choices=("mixed", "flip"), default="mixed",
                            help="mixed: bit flips, drops and insertions in equal shares "
                            "(default); flip: bit flips only")
    link_bench.add_argument("--proto", type=int, choices=(1, 2, 3, 4, 5), default=5,
                            help="highest protocol version both ends offer (2: whole frames, "
                            "as before version 3; 4: the module's messages in PARTs, the "
                            "base's whole; default 5: PARTs both ways)")
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
