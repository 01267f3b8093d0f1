"""Crafted and damaged references (issue 44): every one refused with a typed error and
quarantined, by the store and by the real daemon, and checking one never takes more memory than
a good one, however large the file claims to be.

A crafted file here is made as someone who knows the format would make it: the header declares
the arrays as they are and the checksum is recomputed, so only the checks of what the file
holds stand between it and the service.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO, SIM_FIXTURES
from daemon_rig import Daemon

from hw.depth import open_depth
from robot_change import npzfile
from robot_change.change.scene import SceneModel, build_scene
from robot_change.errors import ReferenceMissing
from robot_change.service.store import ReferenceStore

#: The side of the depth image the crafted large file declares (the issue's: 512 MB of zeros
#: that deflate to ~0.5 MB).
HUGE = 16000


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    """A real reference of the bundled VGA room, saved."""
    with open_depth(str(SIM_FIXTURES / "frames" / "room_vga.png")) as source:
        frame = next(iter(source))
    path = tmp_path_factory.mktemp("good") / "good.scene.npz"
    build_scene([frame], source="good").save(path)
    return path


def _read(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: np.array(data[k]) for k in data.files}
    return json.loads(str(arrays.pop("header")[()])), arrays


def _write(path: Path, header: dict, arrays: dict[str, np.ndarray]) -> None:
    header = dict(header, arrays={k: [a.dtype.str, list(a.shape)] for k, a in arrays.items()})
    header["sha256"] = npzfile.checksum(header, arrays)
    np.savez_compressed(path, header=np.array(json.dumps(header)), **arrays)


def _huge_depth(good: Path, out: Path) -> None:
    """``good`` with a HUGE x HUGE depth image of zeros, declared and checksummed, streamed to
    disk (the file is ~0.5 MB; nothing of its size is ever held here)."""
    header, arrays = _read(good)
    arrays.pop("depth")
    shape = (HUGE, HUGE)
    chunk = np.zeros((1000, HUGE), "<u2")
    listed = {k: [a.dtype.str, list(a.shape)] for k, a in arrays.items()}
    header = dict(header, arrays={**listed, "depth": ["<u2", list(shape)]})
    h = hashlib.sha256()
    body = {k: v for k, v in header.items() if k != "sha256"}
    h.update(json.dumps(body, sort_keys=True).encode())
    for name in sorted([*arrays, "depth"]):
        if name == "depth":
            h.update(f"\ndepth {chunk.dtype.str} {shape}\n".encode())
            for _ in range(HUGE // 1000):
                h.update(chunk.view(np.uint8))
        else:
            a = arrays[name]
            h.update(f"\n{name} {a.dtype.str} {a.shape}\n".encode())
            h.update(np.ascontiguousarray(a).reshape(-1).view(np.uint8))
    header["sha256"] = h.hexdigest()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as archive:
        with archive.open("header.npy", "w") as f:
            np.lib.format.write_array(f, np.array(json.dumps(header)))
        for name, a in arrays.items():
            with archive.open(f"{name}.npy", "w") as f:
                np.lib.format.write_array(f, a)
        with archive.open("depth.npy", "w", force_zip64=True) as f:
            np.lib.format.write_array_header_1_0(
                f, {"descr": "<u2", "fortran_order": False, "shape": shape})
            for _ in range(HUGE // 1000):
                f.write(chunk.tobytes())


def _header(edit):
    def craft(header, arrays):
        edit(header)
    return craft


def _no_points(header, arrays):
    for name in ("points", "keys", "counts"):
        arrays[name] = arrays[name][:0]
    arrays["pixel_voxel"] = np.full_like(arrays["pixel_voxel"], -1)
    arrays["plane_inliers"] = arrays["plane_inliers"][:0]
    header["cloud"]["plane_n_inliers"] = 0


def _nan_points(header, arrays):
    arrays["points"] = arrays["points"].copy()
    arrays["points"][::7] = np.nan


def _no_components(header, arrays):
    for name in ("weights", "means", "covariances"):
        arrays[name] = arrays[name][:0]


def _far_mean(header, arrays):
    arrays["means"] = arrays["means"].copy()
    arrays["means"][0] = 1e300  # finite, so it passed; the ground distances overflowed


def _wide_component(header, arrays):
    arrays["covariances"] = arrays["covariances"].copy()
    arrays["covariances"][0] = np.eye(3) * 1e6  # a component a kilometre wide


#: name -> (how the good file is changed, what the refusal says).
CRAFTED = {
    "infinite plane_n_inliers": (
        _header(lambda h: h["cloud"].update(plane_n_inliers=float("inf"))), "plane_n_inliers"),
    "infinite stage count": (
        _header(lambda h: h["cloud"]["stage_counts"].update(pixels=float("inf"))),
        "stage_counts.pixels"),
    "fractional n_frames": (_header(lambda h: h.update(n_frames=2.5)), "n_frames = 2.5"),
    "boolean iterations": (_header(lambda h: h["cloud"].update(plane_iterations=True)),
                           "plane_iterations"),
    "NaN seconds": (_header(lambda h: h["seconds"].update(fit=float("nan"))), "seconds.fit"),
    "a 16000 x 16000 camera": (
        _header(lambda h: h["intrinsics"].update(width=HUGE, height=HUGE, cx=8000.0,
                                                 cy=8000.0)), "more than the"),
    "depth larger than the camera": (
        lambda h, a: a.update(depth=np.zeros((960, 1280), np.uint16)), "expected (480, 640)"),
    "a 20 MB header": (_header(lambda h: h.update(note="x" * 5_000_000)), "header declares"),
    "NaN points": (_nan_points, "NaN"),
    "no points": (_no_points, "holds 0 points"),
    "no components": (_no_components, "0 mixture components"),
    "a mean at 1e300 m": (_far_mean, "means lie outside the cloud"),
    "a component 1 km wide": (_wide_component, "wider than the cloud"),
}


def _craft(good: Path, out: Path, name: str) -> None:
    if name == "huge depth":
        _huge_depth(good, out)
        return
    header, arrays = _read(good)
    CRAFTED[name][0](header, arrays)
    _write(out, header, arrays)


@pytest.mark.parametrize("name", sorted(CRAFTED))
def test_a_crafted_reference_is_refused_and_quarantined(tmp_path, good, name):
    store = ReferenceStore(tmp_path)
    store.root.mkdir(exist_ok=True)
    _craft(good, store.path("dock"), name)
    crafted = store.path("dock").read_bytes()
    with pytest.raises(ReferenceMissing, match=re.escape(CRAFTED[name][1])) as info:
        store.load("dock")
    assert info.value.quarantined.read_bytes() == crafted
    assert not store.path("dock").exists()
    store.save("dock", SceneModel.load(good))  # the station is not stuck
    assert store.load("dock").source == "good"


def test_the_unchanged_file_loads(tmp_path, good):
    """The crafting itself is sound: re-declared and re-hashed unchanged, the file loads."""
    header, arrays = _read(good)
    _write(tmp_path / "same.scene.npz", header, arrays)
    assert SceneModel.load(tmp_path / "same.scene.npz").source == "good"


CHECK = """
import sys
from robot_change.errors import ReferenceMissing
from robot_change.service.store import ReferenceStore
store = ReferenceStore(sys.argv[1])
try:
    store.load("dock")
    outcome = "loaded"
except ReferenceMissing:
    outcome = "refused"
# VmHWM, not getrusage's ru_maxrss: Linux keeps that across fork and exec (the parent's peak)
peak = next(line for line in open("/proc/self/status") if line.startswith("VmHWM:"))
print(outcome, int(peak.split()[1]) / 1024)
"""


def _check_in_a_process(root: Path) -> tuple[str, float]:
    """Load station dock in a fresh process: ("loaded" or "refused", its peak RSS in MB)."""
    out = subprocess.run([sys.executable, "-c", CHECK, str(root)], cwd=REPO, check=True,
                         capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": str(REPO)}).stdout.split()
    return out[0], float(out[1])


def test_a_reference_declaring_16000_x_16000_is_refused_within_the_memory_of_a_good_one(
        tmp_path, good):
    """The issue's file: 0.5 MB on disk, 512 MB of depth declared (the check grew to 1.1 GB)."""
    good_root, huge_root = tmp_path / "good", tmp_path / "huge"
    for root in (good_root, huge_root):
        root.mkdir()
    (good_root / "dock.scene.npz").write_bytes(good.read_bytes())
    _huge_depth(good, huge_root / "dock.scene.npz")
    assert (huge_root / "dock.scene.npz").stat().st_size < 4_000_000
    outcome, good_mb = _check_in_a_process(good_root)
    assert outcome == "loaded"
    outcome, huge_mb = _check_in_a_process(huge_root)
    assert outcome == "refused"
    assert huge_mb < 300 and huge_mb < good_mb + 20, (good_mb, huge_mb)
    [moved] = ReferenceStore(huge_root).info("dock").quarantined
    assert "declare" in moved.with_name(moved.name + ".txt").read_text()


def test_the_daemon_refuses_crafted_references_and_captures_over_them(tmp_path, good):
    """The real daemon, one station per crafted file: every CHECK a FAULT REFERENCE_MISSING
    (no INTERNAL_ERROR, no CAMERA_LOST), the file quarantined, the daemon's memory high-water
    mark unmoved by the 16000 x 16000 one, and a CAPTURE then replaces the file."""
    refs = tmp_path / "state" / "references"
    refs.mkdir(parents=True)
    stations = {"huge": "huge depth", "inf": "infinite plane_n_inliers", "nan": "NaN points",
                "empty": "no points"}
    for station, name in stations.items():
        _craft(good, refs / f"{station}.scene.npz", name)
    with Daemon(tmp_path) as d:
        d.wait_for("READY=1")
        hwm = _vm_hwm_mb(d.proc.pid)
        script = "".join(f"check {s}\nexpect FAULT code=REFERENCE_MISSING 20\n" for s in stations)
        assert d.base(script) == 0, d.transcript.getvalue() + d.log()
        assert _vm_hwm_mb(d.proc.pid) < hwm + 20, (hwm, _vm_hwm_mb(d.proc.pid))
        assert d.base("""
            watch inf
            expect FAULT code=REFERENCE_MISSING 10
            capture inf
            expect CAPTURED station=inf 20
            check inf
            expect CLEAR station=inf 20
        """) == 0, d.transcript.getvalue() + d.log()
        assert d.first("FAULT", code=_fault_code("INTERNAL_ERROR")) is None
        assert d.first("FAULT", code=_fault_code("CAMERA_LOST")) is None
        log = d.log()
    assert "Traceback" not in log, log
    quarantined = sorted(p.name.split(".")[0] for p in (refs / "quarantine").iterdir()
                         if not p.name.endswith(".txt"))
    assert quarantined == sorted(stations)


def _vm_hwm_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmHWM")


def _fault_code(name: str):
    from robot_change.link.protocol import FaultCode

    return FaultCode[name]
