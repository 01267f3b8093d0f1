"""The ``robot-change`` command line, run as a real subprocess like a user runs it."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import REPO, strict_loads

from hw.imagefile import read_image, write_png
from hw.oni import write_oni


def run(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "robot_change.cli", *args],
        cwd=REPO, capture_output=True, text=True, timeout=timeout,
    )


def test_cloud_writes_points_and_a_picture_of_the_bundled_frame(tmp_path):
    result = run("cloud", "--source", "sim_fixtures/frames/room_vga.png", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    assert "kept" in result.stdout and "plane" in result.stdout
    cloud = np.load(tmp_path / "cloud.npy")
    assert cloud.dtype == np.float32 and cloud.ndim == 2 and cloud.shape[1] == 3
    assert 10_000 < len(cloud) < 30_000  # a room-sized view at the default leaf
    picture = (tmp_path / "cloud.png").read_bytes()
    assert picture.startswith(b"\x89PNG\r\n\x1a\n") and len(picture) > 20_000


def test_cloud_json_on_a_fused_folder(tmp_path):
    depth = np.zeros((120, 160), np.uint16)
    depth[:, :] = 2000  # a wall 2 m away ...
    depth[40:80, 60:100] = 1500  # ... with a box in front of it
    for k in range(3):
        write_png(tmp_path / f"frame_{k}.png", depth)
    result = run("cloud", "--source", f"images:{tmp_path}", "--frames", "3", "--json",
                 "--intrinsics", "131.25,131.25,79.5,59.5")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["frames"] == 3 and summary["size"] == [160, 120]
    assert summary["stage_counts"]["pixels"] == 160 * 120
    assert summary["plane"] is not None and abs(summary["plane"]["distance_m"] - 2.0) < 0.02
    assert set(summary["timings_ms"]) == {"voxel_ms", "outlier_ms", "plane_ms", "preprocess_ms"}


def test_bench_json_has_the_promised_keys():
    result = run("bench", "--json", "--runs", "3")
    assert result.returncode == 0, result.stderr
    figures = json.loads(result.stdout)
    for key in ("points_ms", "voxel_ms", "outlier_ms", "plane_ms", "preprocess_ms",
                "n_points_in", "n_points_out", "em_iter_ms", "fit_ms", "fit_k", "emd_10x10_us",
                "greedy_both_ways_k30_ms", "detect_ms", "capture_ms", "capture_fit_ms",
                "capture_save_ms", "machine"):
        assert key in figures
    assert figures["n_points_in"] > figures["n_points_out"] > 0
    assert figures["preprocess_ms"] > 0
    assert 10_000 < figures["fit_points"] < 30_000 and figures["fit_k"] >= 1
    assert figures["detect_regions"] == 1  # the box that appears in office_box_added
    # the capture's parts are inside its whole, and it built the same reference as the fit
    parts = sum(figures[f"capture_{part}_ms"] for part in ("fusion", "cloud", "fit", "save"))
    assert 0 < parts <= figures["capture_ms"] * 1.5
    assert figures["capture_points"] == figures["fit_points"]


def test_record_converts_images_to_an_oni_that_plays_back(tmp_path):
    frames = [np.full((48, 64), 1000 + 10 * k, np.uint16) for k in range(4)]
    for k, frame in enumerate(frames):
        write_png(tmp_path / f"f{k}.png", frame)
    out = tmp_path / "rec.oni"
    result = run("record", "--source", f"images:{tmp_path}", "--out", str(out), "--frames", "3")
    assert result.returncode == 0, result.stderr
    assert "wrote 3 frame(s)" in result.stdout
    copy = tmp_path / "copy"
    copy.mkdir()
    result = run("record", "--source", str(out), "--out", str(copy / "again.oni"))
    assert result.returncode == 0, result.stderr
    assert "wrote 3 frame(s)" in result.stdout


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("name", ["live.oni", "live"])
def test_record_stopped_by_a_signal_keeps_a_playable_file_and_leaves_nothing_else(tmp_path,
                                                                                  sig, name):
    """Ctrl-C (SIGINT) and kill / systemctl stop (SIGTERM) mid-recording of a live camera
    (OpenNI's DummyDevice): exit 0, the frames so far finished into an .oni that libOpenNI2
    plays, or a ROS 2 bag folder that rosbags reads, no temp file, no leaked shared memory."""
    import signal
    import time

    from hw.depth import open_depth

    out = tmp_path / name
    proc = subprocess.Popen([sys.executable, "-m", "robot_change.cli", "record", "--source",
                             "openni2://Oz", "--out", str(out)], cwd=REPO, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    while not any(p.name.endswith(".tmp") for p in tmp_path.iterdir()):  # frames flowing
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.05)
    time.sleep(0.5)
    proc.send_signal(getattr(signal, sig))
    stdout, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 0, stderr
    assert "leaked" not in stderr and "Traceback" not in stderr, stderr
    assert [p.name for p in tmp_path.iterdir()] == [name]
    written = int(stdout.split("wrote ")[1].split(" frame")[0])
    assert written >= 2
    with open_depth(str(out)) as source:  # .oni, or a folder holding metadata.yaml: a bag
        played = sum(1 for _ in source)
    assert played == written


def test_version_and_the_logging_options_on_every_command():
    from robot_change import __version__

    result = run("--version")
    assert result.returncode == 0 and result.stdout.strip() == f"robot-change {__version__}"
    for command in ("cloud", "capture", "detect", "record", "run", "bench", "demo", "warm-up",
                    "check-config", "list-devices", "link-bench", "base-sim"):
        text = run(command, "--help").stdout
        assert "--log-level" in text and "-q" in text, command
    # -q silences the warning about a source shorter than --frames; without it, it is a
    # timestamped log line
    loud = run("cloud", "--source", "sim_fixtures/frames/room_vga.png", "--frames", "2")
    quiet = run("cloud", "--source", "sim_fixtures/frames/room_vga.png", "--frames", "2", "-q")
    assert "ended after 1 of the 2 frames" in loud.stderr and quiet.stderr == ""
    assert loud.stderr[:4].isdigit()  # "2026-..." when not under the journal


def test_detect_exit_code_tells_change_from_no_change():
    changed = run("detect", "--reference", str(SCENES / "office_box_added" / "reference.oni"),
                  "--current", str(SCENES / "office_box_added" / "current.oni"), "--frames",
                  "3", "--exit-code")
    same = run("detect", "--reference", str(SCENES / "office_no_change" / "reference.oni"),
               "--current", str(SCENES / "office_no_change" / "current.oni"), "--frames", "3",
               "--exit-code")
    plain = run("detect", "--reference", str(SCENES / "office_box_added" / "reference.oni"),
                "--current", str(SCENES / "office_box_added" / "current.oni"), "--frames", "3")
    assert (changed.returncode, same.returncode, plain.returncode) == (1, 0, 0), (
        changed.stderr, same.stderr)


def test_bench_text_keeps_keys_and_values_apart():
    result = run("bench", "--runs", "1")
    assert result.returncode == 0, result.stderr
    for line in result.stdout.splitlines():
        key, _, value = line.partition(" ")
        assert key and value.strip(), line  # a space after every key, however long


def test_warm_up_compiles_or_loads_the_kernels_and_says_where():
    result = run("warm-up", timeout=600)
    assert result.returncode == 0, result.stderr
    assert "kernels ready in" in result.stdout and "cache:" in result.stdout


def test_list_devices_without_a_camera_says_so():
    result = run("list-devices", "--json")
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout) == {"devices": []}
    result = run("list-devices")
    assert "no OpenNI2 camera found" in result.stdout


@pytest.mark.parametrize(
    "args, message",
    [
        (["cloud", "--source", "kinect://0"], "unknown scheme"),
        (["cloud", "--source", "/nonexistent/frame.png"], "/nonexistent/frame.png"),
        (["cloud", "--source", "images:/nonexistent/dir/"], "/nonexistent/dir"),
        (["cloud", "--source", "sim_fixtures/frames/room_vga.png", "--leaf", "-1"], "leaf_m"),
        (["cloud", "--source", "sim_fixtures/frames/room_vga.png", "--frames", "0"], "--frames"),
        (["cloud", "--source", "sim_fixtures/frames/room_vga.png", "--intrinsics", "1,2"],
         "fx,fy,cx,cy"),
        (["record", "--source", "sim_fixtures/frames/room_vga.png", "--out", "/nonexistent/x.oni"],
         "/nonexistent"),
        (["capture", "--source", "sim_fixtures/frames/room_vga.png", "--out",
          "/nonexistent/x.scene.npz"], "the folder /nonexistent does not exist"),
        (["cloud", "--source", "sim_fixtures/frames/room_vga.png", "--out", "/dev/null/x"],
         "--out /dev/null/x: cannot make the folder"),
        (["detect", "--reference", "{scene}", "--current", "sim_fixtures/frames/room_vga.png",
          "--out", "/dev/null/x"], "--out /dev/null/x: cannot make the folder"),
        (["detect", "--reference", "{scene}", "--current", "sim_fixtures/frames/room_vga.png",
          "--out", "{pcd}"], "cloud.pcd: is a file; this command writes a folder"),
        (["cloud", "--source", "sim_fixtures/frames/room_vga.png", "--leaf", "0"],
         "--leaf 0: must be"),
        (["calibrate", "--source", "sim_fixtures/frames/room_vga.png", "--frames", "1", "--out",
          "{pcd}.json"], "needs at least 2"),
        (["bench", "--runs", "0"], "--runs: 0: must be at least 1"),
        (["link-bench", "--count", "zero"], "'zero' is not a whole number"),
        (["cloud", "--source", "{pcd}"], "cloud.pcd: not a PCD file"),
        (["detect", "--reference", "/nonexistent/dock.scene.npz", "--current",
          "sim_fixtures/frames/room_vga.png"], "/nonexistent/dock.scene.npz: No such file"),
        (["detect", "--reference", "{text}", "--current", "sim_fixtures/frames/room_vga.png"],
         "not an .npz archive"),
        (["fleet-tail", "--broker", "http://broker"], "must be a broker URL mqtt://HOST"),
        (["fleet-tail", "--broker", "mqtt://127.0.0.1:1"], "connection refused; is the broker"),
        (["fleet-tail", "--broker", "mqtt://127.0.0.1:1", "--username", "u", "--password-file",
          "/nonexistent/pw"], "cannot read the password file /nonexistent/pw ("),
        (["fleet-tail", "--broker", "mqtt://127.0.0.1:1", "--username", "u", "--password-file",
          "/nonexistent/pw"], "check --password-file and"),  # its option, not the daemon's key
        (["fleet-tail", "--broker", "mqtt://127.0.0.1:1", "--robot", "a/b"], "fleet-tail.robot"),
    ],
)
def test_bad_input_is_a_clear_error_with_exit_status_2(args, message, tmp_path):
    (tmp_path / "cloud.pcd").write_text("# .PCD v0.7 - Point Cloud Data file format\n")
    (tmp_path / "notes.scene.npz").write_text("not a scene\n")
    if "{scene}" in args:
        made = run("capture", "--source", "sim_fixtures/frames/room_vga.png", "--frames", "1",
                   "--out", str(tmp_path / "room.scene.npz"))
        assert made.returncode == 0, made.stderr
    args = [a.format(scene=tmp_path / "room.scene.npz", pcd=tmp_path / "cloud.pcd",
                     text=tmp_path / "notes.scene.npz") for a in args]
    result = run(*args)
    assert result.returncode == 2, (result.stdout, result.stderr)
    assert message in result.stderr
    assert "Traceback" not in result.stderr


def test_depth_in_other_units_than_the_scale_says_is_refused_naming_scale(shared_data):
    """A TUM depth image (5000 units per metre) read as millimetres: 5-30 m readings, which gave
    "0 points -> 0 kept" and exit 0; now an error that names ?scale=, and with it, a cloud."""
    tum = shared_data / "open3d-tum-sample" / "TUM_depth.png"
    result = run("cloud", "--source", str(tum))
    assert result.returncode == 2 and "?scale=" in result.stderr, result.stderr
    result = run("cloud", "--source", f"{tum}?scale=5000")
    assert result.returncode == 0 and " 0 kept" not in result.stdout, result.stderr


def test_a_source_shorter_than_frames_is_said(tmp_path):
    result = run("capture", "--source", "sim_fixtures/frames/room_vga.png", "--frames", "3",
                 "--out", str(tmp_path / "one.scene.npz"))
    assert result.returncode == 0, result.stderr
    assert "ended after 1 of the 3 frames" in result.stderr


def test_one_image_with_the_default_frames_is_used_without_a_warning(tmp_path):
    """--frames not given: a still (one image, one cloud) is what the user meant; said only
    at -v."""
    image = "sim_fixtures/frames/room_vga.png"
    result = run("detect", "--reference", image, "--current", image, "--no-picture")
    assert result.returncode == 0, result.stderr
    assert "ended after" not in result.stderr and "WARNING" not in result.stderr
    result = run("detect", "--reference", image, "--current", image, "--no-picture", "-v")
    assert "ended after 1 of the 5 frames" in result.stderr


def test_a_corrupt_oni_is_refused_before_the_native_library_sees_it(tmp_path):
    good = tmp_path / "good.oni"
    write_oni(good, [np.full((48, 64), 900, np.uint16)])
    bad = tmp_path / "bad.oni"
    bad.write_bytes(good.read_bytes()[:100])
    result = run("cloud", "--source", str(bad))
    assert result.returncode == 2
    assert "bad.oni" in result.stderr and "Traceback" not in result.stderr


def test_the_demo_frame_is_a_vga_depth_image():
    depth = read_image(REPO / "sim_fixtures" / "frames" / "room_vga.png")
    assert depth.shape == (480, 640) and depth.dtype == np.uint16


def test_check_config_accepts_the_example_and_refuses_a_bad_file_with_exit_78(tmp_path):
    from robot_change.cli import EXIT_CONFIG
    from robot_change.service.config import EXIT_CONFIG as CONFIG_EXIT

    assert EXIT_CONFIG == CONFIG_EXIT == 78
    result = run("check-config", str(REPO / "systemd" / "robot-change.toml"))
    assert result.returncode == 0, result.stderr
    import tomllib

    from robot_change.service.config import load_config

    printed = tomllib.loads(result.stdout)  # TOML, not Python reprs: it reads back the same
    assert printed == load_config(REPO / "systemd" / "robot-change.toml").as_dict()
    assert "[cloud]" in result.stdout and "leaf_m = 0.03" in result.stdout
    bad = tmp_path / "bad.toml"
    bad.write_text("[cloud]\nleaf_m = -1\n")
    result = run("check-config", str(bad))
    assert result.returncode == 78
    assert "cloud.leaf_m = -1" in result.stderr and "Traceback" not in result.stderr
    # the camera's URI is built as `run` builds it (not opened): its options are checked too
    bad.write_text(f"[camera]\nsource = 'oni:{SCENES / 'office_box_added' / 'current.oni'}"
                   "?lopp=1'\n[store]\nstate_dir = " + repr(str(tmp_path)) + "\n")
    result = run("check-config", str(bad))
    assert result.returncode == 78 and "unknown OpenNI2 option 'lopp'" in result.stderr
    bad.write_text("[camera]\nsource = 'oni:/media/usb/missing.oni'\n[store]\nstate_dir = "
                   + repr(str(tmp_path)) + "\n")
    result = run("check-config", str(bad))  # a missing file: a FAULT at run, and a note now
    assert result.returncode == 0 and "# note: camera.source: /media/usb/missing.oni does not " \
        "exist now" in result.stdout, result.stdout
    tomllib.loads(result.stdout)  # the notes are comments: the output still reads back


def test_check_config_notes_a_password_sent_in_clear_text(tmp_path):
    (tmp_path / "pw").write_text("hunter2\n")
    notes = {}
    for url in ("mqtt://broker.lan", "mqtts://broker.lan", "mqtt://localhost"):
        path = tmp_path / "fleet.toml"
        path.write_text(f'[store]\nstate_dir = "{tmp_path}"\n[fleet]\nbroker = "{url}"\n'
                        'username = "r7"\npassword_file = "pw"\n')
        result = run("check-config", str(path))
        assert result.returncode == 0, result.stderr
        notes[url] = [line for line in result.stdout.splitlines() if "clear text" in line]
    assert notes["mqtt://broker.lan"] == ["# note: fleet.broker: the password goes to broker.lan "
                                          "in clear text over mqtt://: use mqtts:// "
                                          '(docs/deployment.md, "A fleet on an MQTT broker")']
    assert notes["mqtts://broker.lan"] == notes["mqtt://localhost"] == []


SCENES = REPO / "sim_fixtures" / "scenes"


def test_detect_finds_the_added_box_and_writes_points_report_and_picture(tmp_path):
    scene = SCENES / "office_box_added"
    result = run("detect", "--reference", str(scene / "reference.oni"),
                 "--current", str(scene / "current.oni"), "--out", str(tmp_path), "--json")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["changed"] is True and summary["seconds"] > 0
    [region] = summary["regions"]
    assert region["kind"] == "appeared"
    truth = json.loads((scene / "scene.json").read_text())["changes"][0]["after"]
    # the visible surface's centroid: what a depth camera can locate
    assert np.linalg.norm(np.subtract(region["centroid_m"], truth["visible_centroid_m"])) < 0.1
    appeared = np.load(tmp_path / "appeared.npy")
    assert appeared.dtype == np.float32 and appeared.shape[1] == 3 and len(appeared) > 100
    assert np.load(tmp_path / "disappeared.npy").shape == (0, 3)
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["k_reference"] >= 1 and "detect_ms" in report["timings_ms"]
    assert (tmp_path / "report.png").read_bytes().startswith(b"\x89PNG")


def test_capture_then_detect_against_the_saved_reference_on_an_unchanged_scene(tmp_path):
    scene = SCENES / "office_no_change"
    saved = tmp_path / "office.scene.npz"
    result = run("capture", "--source", str(scene / "reference.oni"), "--out", str(saved))
    assert result.returncode == 0, result.stderr
    assert saved.is_file() and "fused" in result.stdout
    result = run("detect", "--reference", str(saved), "--current", str(scene / "current.oni"))
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("no change")


def test_detect_compares_two_saved_scenes_and_writes_strict_json(tmp_path):
    """Both sides may be saved scenes (the README's detect): each carries its intrinsics.  A
    no-change check's report.json and --json line hold no bare NaN (its greedy EMD has
    nothing to move): strict parsers (JSON.parse, jq) read them."""
    scene = SCENES / "office_no_change"
    saved = {}
    for side in ("reference", "current"):
        saved[side] = tmp_path / f"{side}.scene.npz"
        result = run("capture", "--source", str(scene / f"{side}.oni"), "--out",
                     str(saved[side]))
        assert result.returncode == 0, result.stderr
    out = tmp_path / "check"
    result = run("detect", "--reference", str(saved["reference"]), "--current",
                 str(saved["current"]), "--json", "--out", str(out), "--no-picture")
    assert result.returncode == 0, result.stderr
    line = strict_loads(result.stdout)
    assert line["outcome"] == "no_change" and line["current"] == str(saved["current"])
    assert strict_loads((out / "report.json").read_text())["outcome"] == "no_change"


def test_a_reference_saved_under_any_name_is_read_back_and_a_folder_is_refused(tmp_path):
    """capture --out writes an .npz under whatever name it is given; detect reads it back as
    a scene (an .npz is a zip; no depth file is) rather than asking for a backend.  An --out
    that is a folder is refused naming it, not a temp file."""
    scene = SCENES / "office_no_change"
    plain = tmp_path / "kitchen"
    assert run("capture", "--source", str(scene / "reference.oni"), "--out",
               str(plain)).returncode == 0
    result = run("detect", "--reference", str(plain), "--current", str(scene / "current.oni"))
    assert result.returncode == 0 and result.stdout.startswith("no change"), result.stderr
    result = run("capture", "--source", str(scene / "reference.oni"), "--out", str(tmp_path))
    assert result.returncode == 2 and f"{tmp_path}: is a folder" in result.stderr, result.stderr
    assert ".tmp" not in result.stderr and sorted(p.name for p in tmp_path.iterdir()) == [
        "kitchen"]


def test_detect_json_of_a_check_with_nothing_to_move_is_strict(shared_data):
    """Two frames of the SUN3D study room 1.2 cm apart: no novelty, so the appeared side's
    greedy EMD has nothing to move (NaN); the --json line says null, as JSON allows."""
    frames = shared_data / "sun3d-studyroom-xtion-50f-pose" / "frames"
    given = "?intrinsics=570.342205,570.342205,320,240"
    result = run("detect", "--reference", f"{frames / 'frame-003160.depth.png'}{given}",
                 "--current", f"{frames / 'frame-003161.depth.png'}{given}", "--json")
    assert result.returncode == 0, result.stderr
    line = strict_loads(result.stdout)
    assert line["outcome"] == "no_change"
    assert None in line["greedy_appeared"]["emd_after"] + line["greedy_disappeared"]["emd_after"]


def test_a_killed_capture_leaves_a_temp_file_the_next_one_removes(tmp_path):
    """Issue 44: kill -9 cannot be caught, so a killed ``capture`` leaves its temp file beside
    --out; the next write of the same file removes it (a minute old: no live writer's), and
    spares a fresh one and other files' temp files."""
    import os
    import time

    scene = SCENES / "office_no_change"
    saved = tmp_path / "office.scene.npz"
    dead = tmp_path / ".office.scene.npz.k3j9x.tmp"
    live = tmp_path / ".office.scene.npz.a1b2c.tmp"
    other = tmp_path / ".kitchen.scene.npz.d4e5f.tmp"
    for path in (dead, live, other):
        path.write_bytes(b"half a reference")
    old = time.time() - 120
    os.utime(dead, (old, old))
    os.utime(other, (old, old))
    result = run("capture", "--source", str(scene / "reference.oni"), "--out", str(saved))
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [saved.name, live.name, other.name])


def test_calibrate_measures_a_still_view_and_capture_keeps_the_profile(tmp_path):
    """The office's reference recording (a still camera, independent noise per frame) is
    measured as noisy as the Kinect profile it was rendered with; the profile file it writes
    is what capture uses, told in its summary and kept with the reference; detect's
    report.json tells the profile and what the station can see."""
    from robot_change.change.scene import SceneModel
    from robot_change.noise.profile import NoiseProfile, builtin_profile

    scene = SCENES / "office_no_change"
    camera = tmp_path / "camera.json"
    result = run("calibrate", "--source", str(scene / "reference.oni"), "--out", str(camera),
                 "--json")
    assert result.returncode == 0, result.stderr
    told = json.loads(result.stdout)
    assert told["frames"] == 3 and told["bins"] and told["file"] == str(camera)
    # the recording's 3 frames, not the 30 asked for by default: said
    assert "ended after 3 of the 30 frames asked for" in result.stderr, result.stderr
    profile = NoiseProfile.load(camera)
    kinect = builtin_profile("kinect_v1")
    assert profile.name == "measured:kinect_v1" and profile.measured_use == "replace"
    for z in (2.0, 3.0):
        assert 0.6 < profile.sigma(z) / kinect.sigma(z) < 1.6
    saved = tmp_path / "office.scene.npz"
    result = run("capture", "--source", str(scene / "reference.oni"), "--out", str(saved),
                 "--profile", str(camera))
    assert result.returncode == 0, result.stderr
    assert "noise measured:kinect_v1" in result.stdout and "smallest change seen" in result.stdout
    assert SceneModel.load(saved).noise.measured_use == "replace"
    out = tmp_path / "check"
    result = run("detect", "--reference", str(saved), "--current", str(scene / "current.oni"),
                 "--out", str(out), "--no-picture")
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["noise"]["name"] == "measured:kinect_v1"
    assert report["noise"]["margin_mm"]["2m"] > 30
    assert 50 < report["detection_limit"]["median_mm"] < 200
    bad = run("capture", "--source", str(scene / "reference.oni"), "--out", str(saved),
              "--profile", "kinect_v3")
    assert bad.returncode == 2 and "kinect_v1" in bad.stderr
    missing = run("calibrate", "--source", str(scene / "reference.oni"), "--out",
                  str(tmp_path / "none" / "camera.json"))
    assert missing.returncode == 2 and "Traceback" not in missing.stderr
    # one image looped: the same frame 30 times, no noise to measure
    looped = run("calibrate", "--source", "sim_fixtures/frames/room_vga.png?loop=1", "--out",
                 str(tmp_path / "looped.json"))
    assert looped.returncode == 2 and "frames are identical" in looped.stderr, looped.stderr
    assert not (tmp_path / "looped.json").exists()


def test_calibrate_refuses_frames_of_a_camera_carried_by_hand(tmp_path, shared_data):
    """The SUN3D study room, an Xtion carried ~1 cm a frame: sigma 15-20 times the Xtion's
    (under the 20 times that says the view moved), but the frames drift (9 against 1 for
    noise alone): refused, no profile written."""
    out = tmp_path / "camera.json"
    result = run("calibrate", "--source", str(shared_data / "sun3d-studyroom-xtion-50f-pose"
                                              / "frames"), "--out", str(out))
    assert result.returncode == 2 and "moved steadily" in result.stderr, result.stderr
    assert "Traceback" not in result.stderr and not out.exists()
    # PCL's grabber frames, three of a Kinect held by hand (3-10 mm apart): drift 1.62 over
    # 3 frames (noise alone about 1), sigma 17 times the Kinect's; a profile was written
    result = run("calibrate", "--source", str(shared_data / "pcl-grabber-seq"), "--out",
                 str(out))
    assert result.returncode == 2 and "moved steadily" in result.stderr, result.stderr
    assert not out.exists()


def test_capture_says_when_the_view_moved_while_its_frames_were_taken(tmp_path, shared_data):
    """The SUN3D frames, an Xtion carried by hand: the capture is written (a robot's base
    decides) but says its drift (3.5 over 5 frames) and what it did to the reference."""
    out = tmp_path / "moved.scene.npz"
    result = run("capture", "--source", str(shared_data / "sun3d-studyroom-xtion-50f-pose"
                                            / "frames"), "--out", str(out))
    assert result.returncode == 0 and out.is_file(), result.stderr
    assert "drift 3.50" in result.stdout and "the view moved while" in result.stderr
    still = run("capture", "--source", str(SCENES / "office_no_change" / "reference.oni"),
                "--out", str(tmp_path / "still.scene.npz"))
    assert "drift 1.00" in still.stdout and "moved" not in still.stderr


def test_detect_refuses_a_current_taken_with_other_intrinsics(tmp_path):
    scene = SCENES / "office_box_added"
    result = run("detect", "--reference", str(scene / "reference.oni"),
                 "--current", str(scene / "current.oni"), "--intrinsics", "500,500,320,240")
    # the override applies to both: consistent, so it runs
    assert result.returncode == 0, result.stderr
    saved = tmp_path / "ref.scene.npz"
    assert run("capture", "--source", str(scene / "reference.oni"), "--out",
               str(saved)).returncode == 0
    result = run("detect", "--reference", str(saved), "--current", str(scene / "current.oni"),
                 "--intrinsics", "500,500,320,240")
    assert result.returncode == 2
    assert "intrinsics" in result.stderr and "Traceback" not in result.stderr
    # the reference's intrinsics told to the digit: passing them is accepted
    odd = tmp_path / "odd.scene.npz"
    assert run("capture", "--source", str(scene / "reference.oni"), "--intrinsics",
               "570.342205,570.342205,320.25,240", "--out", str(odd)).returncode == 0
    result = run("detect", "--reference", str(odd), "--current", str(scene / "current.oni"))
    told = result.stderr.split("give the reference's intrinsics ")[1].split()[0]
    assert result.returncode == 2 and told == "570.342205,570.342205,320.25,240"
    assert run("detect", "--reference", str(odd), "--current", str(scene / "current.oni"),
               "--intrinsics", told).returncode == 0
    # another image size: no intrinsics would do, none is suggested
    small = tmp_path / "small.png"
    write_png(small, np.full((240, 320), 2000, np.uint16))
    result = run("detect", "--reference", str(saved), "--current", str(small))
    assert result.returncode == 2 and "images differ" in result.stderr, result.stderr
    assert "--intrinsics" not in result.stderr


def test_detect_refuses_a_truncated_reference_file(tmp_path):
    bad = tmp_path / "bad.scene.npz"
    bad.write_bytes(b"PK\x03\x04 not really a zip")
    scene = SCENES / "office_box_added"
    result = run("detect", "--reference", str(bad), "--current", str(scene / "current.oni"))
    assert result.returncode == 2
    assert "bad.scene.npz" in result.stderr and "Traceback" not in result.stderr
