"""The commands that measure or exercise the module from outside: ``bench`` (the pipeline's
speed on the bundled fixtures), ``base-sim`` (a simulated base controller), ``fleet-tail``
(the fleet's messages from a broker) and ``link-bench`` (the serial link through a noisy
relay)."""

from __future__ import annotations

import argparse
from typing import Any

from robot_change import validate
from robot_change.commands.common import (
    DEMO_FRAME,
    DETECT_SCENE,
    SIM_FIXTURES,
    _bundled,
    _cloud_params,
    _print_json,
    _read_depth,
)


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
    """PAUSE round trips, reports, CHECKs, restarts, STATUS or a flood over a pty pair through a
    noisy relay."""
    from robot_change.tools.linkbench import run_link_bench

    result = run_link_bench(args.corrupt, args.count, args.baud, args.json, seed=args.seed,
                            mode=args.mode, noise=args.noise, proto=args.proto,
                            regions=args.regions)
    ok = {"pause": result.get("delivered"), "report": result.get("reports_complete"),
          "check": result.get("answered"), "restart": result.get("seen"),
          "status": result.get("answered")}.get(args.mode)
    if args.mode == "flood":
        return 0 if result["answers_dropped"] == 0 else 1
    if args.mode == "idle":
        return 0 if result["link_faults"] == result["base_link_faults"] == 0 else 1
    return 0 if ok == result["sent"] else 1
