"""The views of a check for Foxglove (robot_change.export, [viz]): what one costs and whether it
delays the answer to the base.

    flock /tmp/robot_change_bench.lock .venv/bin/python bench/bench_views.py [--runs 20] [--json]

file     check_messages + CheckFileWriter.write of one check of office_box_added (VGA depth,
         the reference fused from 3 frames, the box appeared): median and max ms of each, and
         the file's size.
answer   In process (bench/bench_service.py's rig: the real service and link, the simulated base
         on a pty pair, frames at 30 fps): CHECK sent -> PAUSE received and -> CHANGE_REPORT
         complete, alternating checks with the views off (keep_checks = 0), with the files
         (keep_checks = 20), and with the files and the live view feeding one subscribed
         WebSocket client; and the time the worker took for each view (service.views.last).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "tests"))

from bench_service import SCENE, InProcess, SwitchingSource, _frames  # noqa: E402

from hw.depth import open_depth  # noqa: E402
from hw.oni import read_oni_frames  # noqa: E402
from robot_change.change.detect import detect_changes  # noqa: E402
from robot_change.change.scene import build_scene  # noqa: E402
from robot_change.export.foxglove import TOPICS, check_messages  # noqa: E402
from robot_change.export.mcap import CheckFileWriter  # noqa: E402
from robot_change.service.config import Config, VizConfig  # noqa: E402
from robot_change.service.core import ServiceOptions  # noqa: E402
from robot_change.service.warmup import warm_up  # noqa: E402


def stats(values: list[float]) -> dict[str, float]:
    return {"n": len(values), "median_ms": round(statistics.median(values), 2),
            "max_ms": round(max(values), 2)}


def bench_file(runs: int) -> dict:
    reference = build_scene(read_oni_frames(str(SCENE / "reference.oni"))[:3])
    depth = read_oni_frames(str(SCENE / "current.oni"))[0].depth
    changes = detect_changes(reference, depth)
    writer = CheckFileWriter()
    made, written, sizes = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(runs + 1):
            t0 = time.perf_counter()
            messages = check_messages(reference, depth, changes, stamp_ns=time.time_ns())
            t1 = time.perf_counter()
            sizes.append(writer.write(Path(tmp) / f"{k}.mcap", messages, time.time_ns()))
            t2 = time.perf_counter()
            if k:  # the first pays for imports and the channels
                made.append((t1 - t0) * 1e3)
                written.append((t2 - t1) * 1e3)
    return {"points": int(len(changes.current_points)), "reference_points": len(reference),
            "messages": stats(made), "write": stats(written), "bytes": sizes[-1]}


def bench_answer(runs: int) -> dict:
    from foxglove_client import FoxgloveClient

    warm_up()
    epochs = {"reference": _frames("reference"), "current": _frames("current")}
    with open_depth(f"oni:{SCENE / 'reference.oni'}") as s:
        camera = s.intrinsics
    out: dict[str, dict] = {}
    for label, viz in (("views_off", VizConfig(keep_checks=0)),
                       ("files", VizConfig(keep_checks=20)),
                       ("files_and_live", VizConfig(keep_checks=20, live=True, live_port=0))):
        source = SwitchingSource(epochs, camera)
        with tempfile.TemporaryDirectory() as tmp, \
                InProcess(source, Path(tmp), Config(viz=viz),
                          ServiceOptions(report_dir=Path(tmp) / "reports")) as rig:
            client = None
            if viz.live:
                client = FoxgloveClient("127.0.0.1", rig.service.views.live.port)
                client.wait_for_channels(set(TOPICS))
                client.subscribe_all()
            rig.do("capture office")
            rig.expect("CAPTURED", 10)
            source.switch("current")
            rig.sim.pump(0.3)
            pauses, reports, views = [], [], []
            for _ in range(runs):
                rig.sim.cursor = len(rig.sim.log)
                before = rig.service.counters["views_written"]
                sent = time.monotonic()
                rig.do("check office")
                pauses.append((rig.expect("PAUSE", 10).t - sent) * 1e3)
                reports.append((rig.expect("REPORT", 10).t - sent) * 1e3)
                if viz.keep_checks:
                    end = time.monotonic() + 10
                    while rig.service.counters["views_written"] == before:
                        assert time.monotonic() < end, "no view written"
                        time.sleep(0.005)
                    views.append(rig.service.views.last["ms"])
                if client is not None:
                    client.receive(set(TOPICS))
                rig.do("resume")
                rig.expect("HEARTBEAT", 2, paused="0")
            if client is not None:
                client.close()
            out[label] = {"check_to_pause": stats(pauses), "check_to_report": stats(reports)}
            if views:
                out[label]["view"] = stats(views)
                out[label]["bytes"] = rig.service.views.last["bytes"]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    result = {"load_at_start": os.getloadavg(), "file": bench_file(args.runs),
              "answer": bench_answer(args.runs), "load_at_end": os.getloadavg()}
    print(json.dumps(result, indent=None if args.json else 1))


if __name__ == "__main__":
    main()
