"""PCD / PLY / npy point files (hw.pointfile), organized PCD clouds as a depth source (hw.pcd),
and ``--format`` of cloud, capture and detect.

Every file written is read back with the libraries made for the format (pypcd4, plyfile), with a
small parser of our own written from the format specifications (an independent check of the
bytes), and with Open3D where it is installed (the ``bench`` extra: ~400 MB, so not part of the
test set-up; those checks skip without it).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO, SIM_FIXTURES

from hw.depth import Intrinsics, open_depth, parse_uri
from hw.errors import BackendUnavailable, DepthFileError, FrameError, UriError
from hw.images import read_depth_image
from hw.oni import read_oni_frames
from hw.pointfile import pose_of_viewpoint, read_pcd, viewpoint_of, write_points

pypcd4 = pytest.importorskip("pypcd4", reason="pypcd4 is a dependency: pip install pypcd4")
plyfile = pytest.importorskip("plyfile", reason="plyfile is in the test extra: pip install "
                              "plyfile")

SCENE = SIM_FIXTURES / "scenes" / "office_box_added"


def open3d_or_skip():
    return pytest.importorskip("open3d", reason="Open3D is the bench extra (~400 MB): pip "
                               "install open3d-cpu to run the Open3D read-back")


# --- an independent reader, from the format specifications --------------------------------
def parse_pcd(path: Path) -> tuple[dict[str, list[str]], list[str], np.ndarray]:
    """(header keys -> values, comment lines, structured array) of a binary PCD."""
    data = path.read_bytes()
    header, comments, offset = {}, [], 0
    while True:
        end = data.index(b"\n", offset)
        line = data[offset:end].decode("ascii")
        offset = end + 1
        if line.startswith("#"):
            comments.append(line[1:].strip())
            continue
        key, *values = line.split()
        header[key] = values
        if key == "DATA":
            break
    assert header["DATA"] == ["binary"]
    kinds = {("F", "4"): "<f4", ("U", "1"): "u1", ("U", "4"): "<u4"}
    dtype = np.dtype([(name, kinds[(kind, size)]) for name, kind, size in
                      zip(header["FIELDS"], header["TYPE"], header["SIZE"], strict=True)])
    count = int(header["POINTS"][0])
    return header, comments, np.frombuffer(data, dtype, count=count, offset=offset)


def parse_ply(path: Path) -> tuple[list[str], np.ndarray]:
    """(comment lines, vertex array) of a binary little-endian PLY with one element."""
    data = path.read_bytes()
    head, _, body = data.partition(b"end_header\n")
    lines = head.decode("ascii").splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    comments = [line[len("comment "):] for line in lines if line.startswith("comment ")]
    count = next(int(line.split()[2]) for line in lines if line.startswith("element vertex"))
    kinds = {"float": "<f4", "uchar": "u1"}
    dtype = np.dtype([(line.split()[2], kinds[line.split()[1]]) for line in lines
                      if line.startswith("property")])
    assert len(body) == count * dtype.itemsize
    return comments, np.frombuffer(body, dtype, count=count)


@pytest.fixture(scope="module")
def points() -> np.ndarray:
    rng = np.random.default_rng(3)
    return (rng.normal(size=(500, 3)) * [1.0, 0.5, 0.8] + [0, 0, 2.5]).astype(np.float32)


POSE = np.array([[0.0, -0.17364818, 0.98480775, 0.2], [-1.0, 0.0, 0.0, 0.0],
                 [0.0, -0.98480775, -0.17364818, 0.5], [0.0, 0.0, 0.0, 1.0]])  # 10 deg pitch


# --- writing --------------------------------------------------------------------------------
def test_pcd_reads_back_with_pypcd4_and_by_the_specification(tmp_path, points):
    path = write_points(tmp_path / "cloud.pcd", points, frame="base_link", pose=POSE,
                        color=(0, 200, 0))
    header, comments, raw = parse_pcd(path)
    assert header["FIELDS"] == ["x", "y", "z", "rgb"] and header["HEIGHT"] == ["1"]
    assert comments[0] == ".PCD v0.7 - Point Cloud Data file format"
    assert comments[1].startswith("frame base_link: the robot's base frame, REP 103")
    np.testing.assert_array_equal(np.stack([raw["x"], raw["y"], raw["z"]], axis=1), points)
    packed = raw["rgb"].view("<u4")
    assert set(packed.tolist()) == {(0 << 16) | (200 << 8) | 0}  # PCL's packed rgb
    cloud = pypcd4.PointCloud.from_path(path)
    np.testing.assert_array_equal(cloud.numpy(("x", "y", "z")), points)
    np.testing.assert_allclose(pose_of_viewpoint(cloud.metadata.viewpoint), POSE, atol=1e-7)
    assert [float(v) for v in header["VIEWPOINT"]] == list(cloud.metadata.viewpoint)


def test_ply_reads_back_with_plyfile_and_by_the_specification(tmp_path, points):
    path = write_points(tmp_path / "cloud.ply", points, color=(220, 0, 0))
    comments, raw = parse_ply(path)
    assert comments[0] == "frame camera_optical: the camera's optical frame, x right, y " \
                          "down, z forward, metres"
    assert comments[1].startswith("viewpoint 0 0 0 1 0 0 0 ")
    np.testing.assert_array_equal(np.stack([raw["x"], raw["y"], raw["z"]], axis=1), points)
    assert {tuple(v) for v in np.stack([raw["red"], raw["green"], raw["blue"]], 1)} == \
        {(220, 0, 0)}
    data = plyfile.PlyData.read(path)
    vertex = data["vertex"]
    np.testing.assert_array_equal(np.stack([vertex["x"], vertex["y"], vertex["z"]], 1), points)
    assert data.comments[:2] == comments[:2]


def test_open3d_reads_what_we_write(tmp_path, points):
    o3d = open3d_or_skip()
    for name in ("cloud.pcd", "cloud.ply"):
        path = write_points(tmp_path / name, points, frame="base_link", pose=POSE,
                            color=(0, 200, 0))
        cloud = o3d.io.read_point_cloud(str(path))
        np.testing.assert_array_equal(np.asarray(cloud.points, np.float32), points)
        np.testing.assert_allclose(np.asarray(cloud.colors), [[0, 200 / 255, 0]] * len(points))
    plain = o3d.io.read_point_cloud(str(write_points(tmp_path / "plain.pcd", points)))
    assert not plain.has_colors() and len(plain.points) == len(points)


def test_npy_is_the_bare_array_as_before(tmp_path, points):
    path = write_points(tmp_path / "cloud.npy", points.astype(np.float64))
    loaded = np.load(path)
    assert loaded.dtype == np.float32 and np.array_equal(loaded, points)


def test_no_points_is_still_a_valid_file(tmp_path):
    empty = np.zeros((0, 3), np.float32)
    header, _, raw = parse_pcd(write_points(tmp_path / "none.pcd", empty))
    assert header["POINTS"] == ["0"] and raw.size == 0
    assert len(plyfile.PlyData.read(write_points(tmp_path / "none.ply", empty))["vertex"]) == 0


def test_viewpoint_is_the_pose_as_a_unit_quaternion():
    rng = np.random.default_rng(9)
    for _ in range(50):
        q = rng.normal(size=4)
        pose = pose_of_viewpoint((*rng.normal(size=3), *q))
        viewpoint = viewpoint_of(pose)
        assert viewpoint[3] >= 0 and abs(np.linalg.norm(viewpoint[3:]) - 1) < 1e-8
        np.testing.assert_allclose(pose_of_viewpoint(viewpoint), pose, atol=1e-7)
    assert viewpoint_of(np.eye(4)) == (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    # 180 degrees about x (PCL's viewer convention): w = 0
    assert viewpoint_of(np.diag([1.0, -1.0, -1.0, 1.0])) == (0, 0, 0, 0, 1, 0, 0)


def test_bad_arguments_and_unwritable_paths_are_typed_errors(tmp_path, points):
    for call, error, text in [
        (lambda: write_points(tmp_path / "c.xyz", points), FrameError, "ends in .npy, .pcd"),
        (lambda: write_points(tmp_path / "c.pcd", points[:, :2]), FrameError, "(M, 3)"),
        (lambda: write_points(tmp_path / "c.pcd", points, frame="map"), FrameError, "map"),
        (lambda: write_points(tmp_path / "c.pcd", points, color=(300, 0, 0)), FrameError,
         "0..255"),
        (lambda: write_points(tmp_path / "c.pcd", points, pose=np.ones((4, 4))), FrameError,
         "not a rotation"),
        (lambda: write_points(tmp_path / "no" / "c.pcd", points), DepthFileError,
         "does not exist"),
    ]:
        with pytest.raises(error) as caught:
            call()
        assert text in str(caught.value)
    assert list(tmp_path.iterdir()) == []


def test_ply_without_plyfile_names_what_to_install(tmp_path):
    """plyfile is GPL-3.0, an optional extra: without it, .ply is a BackendUnavailable (the
    library is made unimportable in a fresh interpreter, as if not installed)."""
    code = ("import sys; sys.modules['plyfile'] = None\n"
            "import numpy as np\nfrom hw.pointfile import write_points\n"
            "from hw.errors import BackendUnavailable\n"
            "try:\n    write_points(sys.argv[1], np.zeros((2, 3)))\n"
            "except BackendUnavailable as exc:\n    print(exc)\n")
    result = subprocess.run([sys.executable, "-c", code, str(tmp_path / "c.ply")], cwd=REPO,
                            capture_output=True, text=True, timeout=60)
    assert "writing .ply needs plyfile (pip install plyfile, or robot-change[ply]" in \
        result.stdout, result.stderr
    assert issubclass(BackendUnavailable, ImportError)


# --- organized PCD as a depth source --------------------------------------------------------
CAMERA = Intrinsics(640, 480, 570.3, 568.1, 314.2, 241.7)


def organized_cloud(depth: np.ndarray, camera: Intrinsics) -> np.ndarray:
    """(H*W, 3) float32 points of a depth image (mm), NaN where it has no reading, row by row
    (the back-projection written out here, apart from the library's)."""
    height, width = depth.shape
    v, u = np.mgrid[0:height, 0:width]
    z = depth.astype(np.float64) / 1000.0
    xyz = np.stack([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z], -1)
    xyz[depth == 0] = np.nan
    return xyz.reshape(-1, 3).astype(np.float32)


def save_pcd(path: Path, xyz: np.ndarray, width: int, height: int,
             viewpoint=(0, 0, 0, 1, 0, 0, 0), encoding="binary_compressed") -> Path:
    """An organized PCD written with pypcd4, as PCL's grabber writes them (with an rgb field)."""
    rgb = np.zeros(len(xyz), np.float32)
    cloud = pypcd4.PointCloud.from_points([xyz[:, 0], xyz[:, 1], xyz[:, 2], rgb],
                                          ("x", "y", "z", "rgb"), (np.float32,) * 4)
    cloud.metadata = cloud.metadata.derive(width=width, height=height,
                                           viewpoint=tuple(float(v) for v in viewpoint))
    cloud.save(path, encoding=pypcd4.Encoding(encoding))
    return path


@pytest.fixture(scope="module")
def frames() -> list:
    return read_oni_frames(SCENE / "reference.oni")


def test_an_organized_pcd_is_its_depth_image_with_fitted_intrinsics(tmp_path, frames):
    depth = frames[0].depth
    path = save_pcd(tmp_path / "view.pcd", organized_cloud(depth, CAMERA), 640, 480)
    with open_depth(f"pcd:{path}") as source:
        frame = source.read()
        assert source.read() is None
    np.testing.assert_array_equal(frame.depth, depth)
    assert frame.intrinsics == CAMERA  # fitted to the points, to 0.001 px
    with open_depth(f"{path}?fx=600&cy=240") as source:  # a bare .pcd path; given ones win
        assert source.intrinsics == Intrinsics(640, 480, 600, 568.1, 314.2, 240)


def test_the_viewpoint_is_applied_both_conventions(tmp_path, frames):
    depth = frames[1].depth
    xyz = organized_cloud(depth, CAMERA).astype(np.float64)
    # the camera at POSE in a base frame: the file holds base-frame points and says so
    moved = (xyz @ POSE[:3, :3].T + POSE[:3, 3]).astype(np.float32)
    based = save_pcd(tmp_path / "base.pcd", moved, 640, 480, viewpoint=viewpoint_of(POSE))
    # PCL's viewer convention: VIEWPOINT 0 0 0 0 1 0 0 with the points as the camera saw them
    viewer = save_pcd(tmp_path / "viewer.pcd", xyz.astype(np.float32), 640, 480,
                      viewpoint=(0, 0, 0, 0, 1, 0, 0), encoding="binary")
    for path in (based, viewer):
        with open_depth(f"pcd:{path}") as source:
            frame = source.read()
        assert np.count_nonzero(frame.depth != depth) < 20, path  # float32 rounding at .5 mm
        assert np.abs(frame.depth.astype(int) - depth).max() <= 1
        np.testing.assert_allclose(frame.intrinsics.as_array(), CAMERA.as_array(), atol=0.01)


def test_an_unorganized_pcd_is_refused_as_a_depth_source(tmp_path, points):
    path = write_points(tmp_path / "scattered.pcd", points)  # HEIGHT 1
    assert read_pcd(path).organized is False
    with pytest.raises(DepthFileError, match="not organized .WIDTH 500, HEIGHT 1."):
        with open_depth(f"pcd:{path}") as source:
            source.read()


def test_a_folder_of_pcds_plays_in_order_with_grabber_timestamps(tmp_path, frames):
    names = ["frame_20121214T142256.068683.pcd", "frame_20121214T142255.814212.pcd"]
    for name, frame in zip(names, frames, strict=False):
        save_pcd(tmp_path / name, organized_cloud(frame.depth, CAMERA), 640, 480)
    (tmp_path / "notes.txt").write_text("not a cloud")
    with open_depth(f"pcd:{tmp_path}?loop=1") as source:
        got = [source.read() for _ in range(3)]
    assert [f.timestamp_us for f in got[:2]] == [1355494975_814212, 1355494976_068683]  # UTC
    assert got[2].timestamp_us > got[1].timestamp_us
    np.testing.assert_array_equal(got[0].depth, frames[1].depth)  # the earlier name first
    np.testing.assert_array_equal(got[1].depth, frames[0].depth)


def test_bad_pcds_and_options_are_typed_errors(tmp_path):
    (tmp_path / "text.pcd").write_text("hello\n")
    (tmp_path / "cut.pcd").write_bytes(
        b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 4\nHEIGHT 2\n"
        b"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 8\nDATA binary\n" + bytes(20))
    (tmp_path / "nofields.pcd").write_bytes(
        b"VERSION 0.7\nFIELDS a\nSIZE 4\nTYPE F\nCOUNT 1\nWIDTH 2\nHEIGHT 2\n"
        b"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 4\nDATA binary\n" + bytes(16))
    (tmp_path / "empty").mkdir()
    for uri, error, text in [
        (f"pcd:{tmp_path / 'text.pcd'}", DepthFileError, "not a PCD file"),
        (f"pcd:{tmp_path / 'cut.pcd'}", DepthFileError, "truncated or broken PCD"),
        (f"pcd:{tmp_path / 'nofields.pcd'}", DepthFileError, "fields a, not x y z"),
        (f"pcd:{tmp_path / 'none.pcd'}", DepthFileError, "no such file or folder"),
        (f"pcd:{tmp_path / 'empty'}", DepthFileError, "looked for *.pcd"),
        (f"pcd:{tmp_path / 'text.pcd'}?fx=-1", UriError, "fx='-1'"),
        (f"pcd:{tmp_path / 'text.pcd'}?scale=2", UriError, "pcd option(s) scale unknown"),
    ]:
        with pytest.raises(error) as caught:
            with open_depth(uri) as source:
                source.read()
        assert text in str(caught.value), (uri, caught.value)
    assert parse_uri(str(tmp_path / "x.pcd"))[0] == "pcd"


def test_real_organized_pcds_match_their_depth_images(shared_data):
    """osd-tabletop (PCL's mOSD test set, BSD-3): the PCD's z is the depth the data set's
    README derived; 525 / 319.5 / 239.5 are fitted.  office1 (PCL's test data) carries a
    viewer-convention VIEWPOINT (0 0 0 0 1 0 0)."""
    folder = shared_data / "osd-tabletop"
    if not (folder / "pcd" / "test9.pcd").is_file():
        pytest.skip(f"{folder} does not hold pcd/test9.pcd")
    with open_depth(f"pcd:{folder / 'pcd' / 'test9.pcd'}") as source:
        frame = source.read()
    np.testing.assert_array_equal(frame.depth,
                                  read_depth_image(folder / "derived" / "test9_depth_mm.png"))
    assert frame.intrinsics == Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)
    office = shared_data / "pcl-kinect-scenes" / "office1.pcd"
    if office.is_file():
        with open_depth(f"pcd:{office}") as source:
            frame = source.read()
        valid = frame.depth[frame.depth > 0]
        assert 0.8 < frame.valid_fraction() < 0.85 and valid.min() >= 1800 and \
            valid.max() <= 5400  # its README: 82.8 % valid, 1.83-5.36 m
        assert frame.intrinsics == Intrinsics(640, 480, 525.0, 525.0, 320.0, 240.0)


# --- the command line -----------------------------------------------------------------------
def run(*args: str, timeout: float = 300.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "robot_change.cli", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


MOUNT = "0.2,0,0.5,0,10,0"


def test_cli_cloud_writes_pcd_in_base_link_and_ply_in_the_camera_frame(tmp_path):
    from robot_change.change.mount import CameraMount

    source = "sim_fixtures/frames/room_vga.png"
    result = run("cloud", "--source", source, "--out", str(tmp_path / "npy"), "--json",
                 "--no-picture")
    assert result.returncode == 0, result.stderr
    optical = np.load(tmp_path / "npy" / "cloud.npy")
    result = run("cloud", "--source", source, "--out", str(tmp_path / "pcd"), "--format", "pcd",
                 "--mount", MOUNT, "--json", "--no-picture")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["frame"] == "base_link"
    header, comments, raw = parse_pcd(tmp_path / "pcd" / "cloud.pcd")
    based = np.stack([raw["x"], raw["y"], raw["z"]], 1)
    mount = CameraMount.parse(MOUNT)
    np.testing.assert_allclose(based, mount.to_base(optical), atol=1e-6)
    np.testing.assert_allclose(pose_of_viewpoint([float(v) for v in header["VIEWPOINT"]]),
                               mount.base_from_optical(), atol=1e-7)
    result = run("cloud", "--source", source, "--out", str(tmp_path / "ply"), "--format", "ply",
                 "--no-picture")
    assert result.returncode == 0, result.stderr
    comments, raw = parse_ply(tmp_path / "ply" / "cloud.ply")
    assert comments[0].startswith("frame camera_optical")
    np.testing.assert_array_equal(np.stack([raw["x"], raw["y"], raw["z"]], 1), optical)


def test_cli_detect_and_capture_write_point_files_and_say_the_frame(tmp_path):
    reference, current = SCENE / "reference.oni", SCENE / "current.oni"
    captured = run("capture", "--source", str(reference), "--frames", "3", "--mount", MOUNT,
                   "--format", "ply", "--out", str(tmp_path / "station.scene.npz"))
    assert captured.returncode == 0, captured.stderr
    assert "station.scene.ply: the clean cloud, base_link frame" in captured.stdout
    comments, raw = parse_ply(tmp_path / "station.scene.ply")
    assert comments[0].startswith("frame base_link") and len(raw) > 10_000
    out = tmp_path / "check"
    result = run("detect", "--reference", str(tmp_path / "station.scene.npz"), "--current",
                 str(current), "--frames", "3", "--format", "pcd", "--out", str(out),
                 "--no-picture")
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["points_frame"] == "base_link"  # the reference's recorded mounting
    assert sorted(p.name for p in out.iterdir()) == ["appeared.pcd", "disappeared.pcd",
                                                     "report.json"]
    header, comments, raw = parse_pcd(out / "appeared.pcd")
    assert int(header["POINTS"][0]) == report["n_appeared_points"] > 0
    assert comments[1].startswith("frame base_link")
    [rgb] = set(raw["rgb"].view("<u4").tolist())
    r, g, b = (rgb >> 16) & 255, (rgb >> 8) & 255, rgb & 255
    assert g > 3 * max(r, b)  # appeared: green, as in report.png and Foxglove
    centroid = np.stack([raw["x"], raw["y"], raw["z"]], 1).mean(axis=0)
    region = report["regions"][0]["base"]
    assert np.all(np.array(region["bbox_min_m"]) - 1e-3 <= centroid)
    assert np.all(centroid <= np.array(region["bbox_max_m"]) + 1e-3)
    # npy stays as it was: the camera optical frame, whatever the mounting
    plain = run("detect", "--reference", str(tmp_path / "station.scene.npz"), "--current",
                str(current), "--frames", "3", "--out", str(tmp_path / "plain"), "--no-picture")
    assert plain.returncode == 0, plain.stderr
    assert json.loads((tmp_path / "plain" / "report.json").read_text())["points_frame"] == \
        "camera_optical"
    appeared = np.load(tmp_path / "plain" / "appeared.npy")
    assert appeared.dtype == np.float32 and len(appeared) == report["n_appeared_points"]
    assert 1.5 < appeared[:, 2].mean() < 3.5  # z forward: in front of the camera


def test_cli_reads_an_organized_pcd(tmp_path, frames):
    path = save_pcd(tmp_path / "view.pcd", organized_cloud(frames[0].depth, CAMERA), 640, 480)
    result = run("cloud", "--source", str(path), "--json")
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["valid_pixels"] == np.count_nonzero(frames[0].depth)
    scattered = write_points(tmp_path / "scattered.pcd", np.ones((10, 3), np.float32))
    result = run("cloud", "--source", f"pcd:{scattered}")
    assert result.returncode == 2 and "not organized" in result.stderr
    assert "Traceback" not in result.stderr
