"""ROS bags as a depth source and ``record`` to a ROS 2 bag (hw.rosbag, hw.record).

Every bag read here is written by rosbags' own writers (ROS 1 ``.bag``, ROS 2 ``.db3`` and
``.mcap``) from the bundled recordings, in a temp folder; every bag we write is read back with
rosbags' own reader.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import REPO, SIM_FIXTURES

from hw.depth import DepthFrame, Intrinsics, open_depth, parse_uri
from hw.errors import DepthFileError, FrameTimeout, UriError
from hw.oni import read_oni_frames
from hw.record import record

rosbags = pytest.importorskip("rosbags", reason="rosbags is a dependency: pip install rosbags")
from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

SCENE = SIM_FIXTURES / "scenes" / "office_box_added"
DEPTH = "/camera/depth/image_raw"
INFO = "/camera/depth/camera_info"
#: A camera other than OpenNI's default, so that the intrinsics are seen to come from the bag.
CAMERA = Intrinsics(640, 480, 570.3, 568.1, 314.2, 241.7)
#: TUM-like header stamps (ns): 1305031102.160407 s, then every 1/30 s (with odd nanoseconds).
STAMPS_NS = [1_305_031_102_160_407_123 + k * 33_333_333 for k in range(3)]
KINDS = ("ros1", "db3", "mcap")


def write_bag(path: Path, kind: str, frames: list[np.ndarray], *, encoding: str = "16UC1",
              topic: str = DEPTH, info_topic: str | None = INFO, camera: Intrinsics = CAMERA,
              model: str = "plumb_bob", distortion=(0.0,) * 5, extra: dict | None = None,
              stamps: list[int] = STAMPS_NS, infos: list | None = None, seqs=None,
              bigendian: bool = False, pad: int = 0, compressed=None) -> Path:
    """A bag written with rosbags' own writer: ``frames`` (H, W) uint16 mm as ``encoding`` on
    ``topic`` and a CameraInfo per frame on ``info_topic``; ``extra``: topic -> (msgtype,
    [messages]) written too.  ``kind``: ros1 (path.bag), db3 or mcap (a ROS 2 folder).
    ``compressed(k, depth) -> (format, bytes)``: a sensor_msgs/CompressedImage of that instead
    of an Image (``topic`` is then the compressed topic)."""
    store = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)
    types = store.types
    Image, Info = types["sensor_msgs/msg/Image"], types["sensor_msgs/msg/CameraInfo"]
    Header, Time = types["std_msgs/msg/Header"], types["builtin_interfaces/msg/Time"]
    ROI = types["sensor_msgs/msg/RegionOfInterest"]

    def header(k: int):
        stamp = Time(sec=stamps[k] // 10**9, nanosec=stamps[k] % 10**9)
        if kind == "ros1":
            return Header(seq=(seqs or range(len(frames)))[k], stamp=stamp,
                          frame_id="camera_depth_optical_frame")
        return Header(stamp=stamp, frame_id="camera_depth_optical_frame")

    def image(k: int, depth: np.ndarray):
        height, width = depth.shape
        if encoding == "32FC1":
            metres = np.where(depth > 0, depth / 1000.0, np.nan).astype(np.float32)
            raw = metres.astype(">f4" if bigendian else "<f4")
        elif encoding == "16UC1":
            raw = depth.astype(">u2" if bigendian else "<u2")
        else:  # a colour image where depth was expected
            raw = np.repeat((depth // 40).astype(np.uint8)[..., None], 3, axis=2)
        rows = raw.view(np.uint8).reshape(height, -1)
        step = rows.shape[1] + pad
        data = np.zeros((height, step), np.uint8)
        data[:, :rows.shape[1]] = rows
        return Image(header=header(k), height=height, width=width, encoding=encoding,
                     is_bigendian=int(bigendian), step=step, data=data.reshape(-1))

    def info(k: int, cam: Intrinsics):
        K = np.array([cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1.0])
        P = np.array([cam.fx, 0, cam.cx, 0, 0, cam.fy, cam.cy, 0, 0, 0, 1.0, 0])
        fields = dict(header=header(k), height=cam.height, width=cam.width,
                      distortion_model=model, binning_x=0, binning_y=0,
                      roi=ROI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
        arrays = {"d": np.array(distortion, float), "k": K, "r": np.eye(3).ravel(), "p": P}
        for name, value in arrays.items():
            fields[name.upper() if kind == "ros1" else name] = value
        return Info(**fields)

    def packed(k: int, depth: np.ndarray):
        text, data = compressed(k, depth)
        return types["sensor_msgs/msg/CompressedImage"](
            header=header(k), format=text, data=np.frombuffer(data, np.uint8))

    serialize = store.serialize_ros1 if kind == "ros1" else store.serialize_cdr
    Image = types["sensor_msgs/msg/CompressedImage"] if compressed else Image
    image = packed if compressed else image
    if kind == "ros1":
        target = path.with_suffix(".bag")
        writer = Writer1(target)
    else:
        target = path
        writer = Writer2(target, version=9, storage_plugin=StoragePlugin.SQLITE3
                         if kind == "db3" else StoragePlugin.MCAP)
    with writer:
        images = writer.add_connection(topic, Image.__msgtype__, typestore=store)
        cameras = (writer.add_connection(info_topic, Info.__msgtype__, typestore=store)
                   if info_topic else None)
        others = {name: (writer.add_connection(name, msgtype, typestore=store), messages)
                  for name, (msgtype, messages) in (extra or {}).items()}
        for k, depth in enumerate(frames):
            if cameras is not None:
                cam = (infos or [camera] * len(frames))[k]
                writer.write(cameras, stamps[k], serialize(info(k, cam), Info.__msgtype__))
            writer.write(images, stamps[k], serialize(image(k, depth), Image.__msgtype__))
        for connection, messages in others.values():
            for k, message in enumerate(messages):
                writer.write(connection, stamps[0] + k, serialize(message, connection.msgtype))
    return target


def image_message(kind: str, depth: np.ndarray, encoding: str):
    """A sensor_msgs/Image of ``depth`` in ``encoding`` (for extra topics)."""
    store = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)
    types = store.types
    stamp = types["builtin_interfaces/msg/Time"](sec=1, nanosec=0)
    header = (types["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id="f") if kind == "ros1"
              else types["std_msgs/msg/Header"](stamp=stamp, frame_id="f"))
    data = depth.astype("<u2").view(np.uint8).reshape(-1) if encoding != "rgb8" else \
        np.zeros(depth.size * 3, np.uint8)
    step = depth.shape[1] * (2 if encoding != "rgb8" else 3)
    return types["sensor_msgs/msg/Image"](header=header, height=depth.shape[0],
                                          width=depth.shape[1], encoding=encoding,
                                          is_bigendian=0, step=step, data=data)


def read_all(uri: str) -> tuple[list[DepthFrame], Intrinsics]:
    with open_depth(uri) as source:
        frames = list(source)
        return frames, source.intrinsics


# --- reading --------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
def test_a_bag_reads_back_exactly(tmp_path, depth_frames, kind):
    bag = write_bag(tmp_path / "run", kind, depth_frames)
    frames, camera = read_all(f"rosbag:{bag}?topic={DEPTH}")
    assert camera == CAMERA
    assert [f.timestamp_us for f in frames] == [(s + 500) // 1000 for s in STAMPS_NS]
    assert [f.index for f in frames] == [0, 1, 2]
    for frame, original in zip(frames, depth_frames, strict=True):
        np.testing.assert_array_equal(frame.depth, original)
        assert frame.intrinsics == CAMERA


@pytest.mark.parametrize("kind", KINDS)
def test_the_only_depth_topic_is_found_without_being_named(tmp_path, depth_frames, kind):
    extra = {"/camera/rgb/image_color": ("sensor_msgs/msg/Image",
                                         [image_message(kind, depth_frames[0], "rgb8")])}
    bag = write_bag(tmp_path / "run", kind, depth_frames[:1], extra=extra)
    frames, _ = read_all(str(bag))  # a bare .bag path, or a folder with metadata.yaml
    assert len(frames) == 1
    np.testing.assert_array_equal(frames[0].depth, depth_frames[0])


def test_a_storage_file_alone_reads_too(tmp_path, depth_frames):
    for kind, suffix in (("mcap", ".mcap"), ("db3", ".db3")):
        bag = write_bag(tmp_path / kind, kind, depth_frames[:2])
        frames, camera = read_all(f"rosbag:{bag / (kind + suffix)}")
        assert camera == CAMERA and len(frames) == 2


@pytest.mark.parametrize("kind", ("ros1", "mcap"))
def test_32fc1_metres_with_nan_read_as_millimetres(tmp_path, depth_frames, kind):
    bag = write_bag(tmp_path / "run", kind, depth_frames, encoding="32FC1", bigendian=True,
                    pad=8)
    frames, _ = read_all(f"rosbag:{bag}")
    for frame, original in zip(frames, depth_frames, strict=True):
        assert np.count_nonzero(original == 0) > 0  # the NaNs are there to be read as 0
        np.testing.assert_array_equal(frame.depth, original)


def test_big_endian_and_padded_rows_of_16uc1(tmp_path, depth_frames):
    bag = write_bag(tmp_path / "run", "ros1", depth_frames, bigendian=True, pad=6)
    frames, _ = read_all(f"rosbag:{bag}")
    for frame, original in zip(frames, depth_frames, strict=True):
        np.testing.assert_array_equal(frame.depth, original)


def test_32fc1_conversion_rounds_and_drops_what_is_no_reading():
    from hw.rosbag import image_to_depth

    class Message:  # the fields of a sensor_msgs/Image, as rosbags gives them
        encoding, height, width, is_bigendian = "32FC1", 1, 7, 0
        step = 28
        data = np.array([0.5004, 1.2346, np.nan, np.inf, -1.0, 0.0, 70.0],
                        np.float32).view(np.uint8)

    np.testing.assert_array_equal(image_to_depth(Message, "test"),
                                  [[500, 1235, 0, 0, 0, 0, 0]])


@pytest.mark.parametrize("kind", ("ros1", "db3"))
def test_a_wrong_or_missing_topic_lists_the_depth_topics(tmp_path, depth_frames, kind):
    extra = {"/camera/depth_registered/image_raw": (
        "sensor_msgs/msg/Image", [image_message(kind, depth_frames[0], "16UC1")]),
        "/camera/rgb/image_color": ("sensor_msgs/msg/Image",
                                    [image_message(kind, depth_frames[0], "rgb8")])}
    bag = write_bag(tmp_path / "run", kind, depth_frames[:1], extra=extra)
    for uri in (f"rosbag:{bag}?topic=/camera/depth/image", f"rosbag:{bag}?topic={INFO}",
                f"rosbag:{bag}"):
        with pytest.raises(DepthFileError) as caught:
            read_all(uri)
        message = str(caught.value)
        assert "Depth image topics in this bag: /camera/depth/image_raw (16UC1), " \
               "/camera/depth_registered/image_raw (16UC1)" in message, message
        assert "/camera/rgb/image_color (rgb8)" in message
    assert "?topic=" in message  # several and none named: say how to choose


def test_a_bag_without_depth_says_what_it_holds(tmp_path, depth_frames):
    bag = write_bag(tmp_path / "run", "mcap", depth_frames[:1], encoding="rgb8",
                    topic="/camera/rgb/image_color", info_topic=None)
    with pytest.raises(DepthFileError, match="no depth image topic.*image_color \\(rgb8\\)"):
        read_all(f"rosbag:{bag}")


@pytest.mark.parametrize("kind", KINDS)
def test_a_wrong_encoding_on_the_topic_is_refused(tmp_path, depth_frames, kind):
    bag = write_bag(tmp_path / "run", kind, depth_frames[:1], encoding="rgb8")
    source = open_depth(f"rosbag:{bag}?topic={DEPTH}")
    with pytest.raises(DepthFileError, match="encoding 'rgb8' is not depth; depth images are "
                                             "16UC1 \\(millimetres\\) or 32FC1 \\(metres\\)"):
        source.open()  # found at open, before any frame is asked for


@pytest.mark.parametrize("kind", ("ros1", "mcap"))
def test_missing_camera_info_is_refused_unless_intrinsics_are_given(tmp_path, depth_frames,
                                                                    kind):
    bag = write_bag(tmp_path / "run", kind, depth_frames[:1], info_topic=None)
    with pytest.raises(DepthFileError) as caught:
        read_all(f"rosbag:{bag}")
    assert "no sensor_msgs/CameraInfo for /camera/depth/image_raw: looked for " \
           "/camera/depth/camera_info" in str(caught.value)
    assert "?info=TOPIC" in str(caught.value) and "?intrinsics=" in str(caught.value)
    frames, camera = read_all(f"rosbag:{bag}?intrinsics=580,581,320,240")
    assert camera == Intrinsics(640, 480, 580, 581, 320, 240) and len(frames) == 1


def test_camera_info_elsewhere_is_named_with_info(tmp_path, depth_frames):
    bag = write_bag(tmp_path / "run", "mcap", depth_frames[:1], info_topic="/calib/depth_info")
    with pytest.raises(DepthFileError, match="CameraInfo topics in this bag: /calib/depth_info"):
        read_all(f"rosbag:{bag}")
    _, camera = read_all(f"rosbag:{bag}?info=/calib/depth_info")
    assert camera == CAMERA


def test_a_distorted_raw_image_is_refused_and_a_rectified_one_uses_p(tmp_path, depth_frames):
    distortion = (0.1, -0.2, 0.001, 0.0, 0.05)
    bag = write_bag(tmp_path / "raw", "mcap", depth_frames[:1], distortion=distortion)
    with pytest.raises(DepthFileError) as caught:
        read_all(f"rosbag:{bag}")
    assert "distortion model 'plumb_bob' with coefficients [0.1, -0.2, 0.001, 0, 0.05]" in \
        str(caught.value) and "?rectified=1" in str(caught.value)
    # the same image declared rectified, by name or by option: P is the camera
    rect = write_bag(tmp_path / "rect", "mcap", depth_frames[:1], distortion=distortion,
                     topic="/camera/depth/image_rect_raw")
    assert read_all(f"rosbag:{rect}")[1] == CAMERA
    assert read_all(f"rosbag:{bag}?rectified=1")[1] == CAMERA
    fisheye = write_bag(tmp_path / "fisheye", "mcap", depth_frames[:1], model="equidistant",
                        distortion=(0.0,) * 4)
    with pytest.raises(DepthFileError, match="distortion model 'equidistant'"):
        read_all(f"rosbag:{fisheye}")


def test_camera_info_that_makes_no_camera_is_refused(tmp_path, depth_frames):
    small = write_bag(tmp_path / "binned", "mcap", depth_frames[:1],
                      camera=Intrinsics(1280, 960, 1140, 1136, 628, 483))
    with pytest.raises(DepthFileError, match="CameraInfo is for 1280x960 images but the depth "
                                             "images are 640x480"):
        read_all(f"rosbag:{small}")
    # an uncalibrated driver publishes K = 0
    uncalibrated = SimpleNamespace(width=640, height=480, fx=0.0, fy=0.0, cx=0.0, cy=0.0)
    zeros = write_bag(tmp_path / "zero", "ros1", depth_frames[:1], infos=[uncalibrated])
    with pytest.raises(DepthFileError, match="uncalibrated camera publishes zeros"):
        read_all(f"rosbag:{zeros}")


def test_camera_info_changing_midway_is_refused_where_it_changes(tmp_path, depth_frames):
    other = Intrinsics(640, 480, 600, 600, 320, 240)
    bag = write_bag(tmp_path / "run", "mcap", depth_frames, infos=[CAMERA, CAMERA, other])
    with open_depth(f"rosbag:{bag}") as source:
        assert source.read() is not None and source.read() is not None
        with pytest.raises(DepthFileError, match="CameraInfo on /camera/depth/camera_info "
                                                 "changes at 1305031102.227 s"):
            source.read()


def test_loop_keeps_indices_and_time_increasing_and_rate_paces(tmp_path, depth_frames):
    bag = write_bag(tmp_path / "run", "mcap", depth_frames)
    with open_depth(f"rosbag:{bag}?loop=1") as source:
        frames = [source.read() for _ in range(7)]
    assert [f.index for f in frames] == list(range(7))
    stamps = [f.timestamp_us for f in frames]
    period = stamps[1] - stamps[0]
    assert stamps[3] - stamps[2] == period  # the next lap starts one period after the last
    assert all(b > a for a, b in zip(stamps, stamps[1:], strict=False))
    for k, frame in enumerate(frames):
        np.testing.assert_array_equal(frame.depth, depth_frames[k % 3])
    with open_depth(f"rosbag:{bag}?rate=0.5") as source:
        assert source.read(timeout=5).index == 0
        with pytest.raises(FrameTimeout, match="paced at 0.5 fps"):
            source.read(timeout=0.01)
        assert source.stats.delivered == 1


def test_gaps_in_ros1_sequence_numbers_count_as_dropped(tmp_path, depth_frames):
    bag = write_bag(tmp_path / "run", "ros1", depth_frames, seqs=[10, 11, 15])
    with open_depth(f"rosbag:{bag}") as source:
        assert len(list(source)) == 3
        assert (source.stats.delivered, source.stats.dropped) == (3, 3)


def test_bad_options_and_paths_are_typed_errors(tmp_path, depth_frames):
    bag = write_bag(tmp_path / "run", "mcap", depth_frames[:1])
    for uri, error, text in [
        (f"rosbag:{bag}?fps=30", UriError, "rosbag option(s) fps unknown"),
        (f"rosbag:{bag}?rate=fast", UriError, "rate='fast'"),
        (f"rosbag:{bag}?intrinsics=1,2", UriError, "fx,fy,cx,cy"),
        (f"rosbag:{bag}?topic=/a b", UriError, "topic name"),
        (f"rosbag:{tmp_path}/none.bag", DepthFileError, "no such file or folder"),
    ]:
        with pytest.raises(error) as caught:
            read_all(uri)
        assert text in str(caught.value)


def test_what_is_not_a_bag_is_a_depth_file_error(tmp_path):
    rng = np.random.default_rng(5)
    for name in ("noise.bag", "noise.mcap", "noise.db3"):
        (tmp_path / name).write_bytes(rng.integers(0, 256, 4000, dtype=np.uint8).tobytes())
        with pytest.raises(DepthFileError, match=f"{name}: not a readable ROS bag"):
            read_all(f"rosbag:{tmp_path / name}")
    (tmp_path / "folder").mkdir()
    with pytest.raises(DepthFileError, match="without metadata.yaml is not a ROS 2 bag"):
        read_all(f"rosbag:{tmp_path / 'folder'}")
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "metadata.yaml").write_text("rosbag2_bagfile_information: [1\n")
    with pytest.raises(DepthFileError, match="not a readable ROS bag"):
        read_all(str(tmp_path / "broken"))


def test_bare_paths_pick_the_rosbag_backend(tmp_path):
    (tmp_path / "bagdir").mkdir()
    (tmp_path / "bagdir" / "metadata.yaml").write_text("x: 1\n")
    assert parse_uri(str(tmp_path / "bagdir"))[0] == "rosbag"
    assert parse_uri(str(tmp_path))[0] == "images"  # a folder without metadata.yaml
    for name in ("a.bag", "b.db3", "c.mcap"):
        assert parse_uri(str(tmp_path / name))[0] == "rosbag"
    assert parse_uri("rosbag:x.bag?topic=/d")[1:] == ("x.bag", {"topic": "/d"})


# --- writing: record to a ROS 2 bag ---------------------------------------------------------
def test_record_to_rosbag2_reads_back_through_rosbags_itself(tmp_path):
    """Every field read back by rosbags; the .oni's stamps (the camera's clock, from 0) moved
    to the time of day of the recording, as ROS tools expect (they showed 1970)."""
    originals = read_oni_frames(SCENE / "current.oni")
    assert originals[0].timestamp_us < 10**7  # the camera's clock
    out = tmp_path / "run1"
    before = time.time_ns() // 1000
    with open_depth(f"oni:{SCENE / 'current.oni'}") as source:
        assert record(source, out, format="rosbag2") == 3
    offset = None
    assert sorted(p.name for p in out.iterdir()) == ["metadata.yaml", "run1.mcap"]
    assert [p.name for p in tmp_path.iterdir()] == ["run1"]  # no temp folder left
    with AnyReader([out]) as reader:
        assert {name: info.msgtype for name, info in reader.topics.items()} == {
            "/camera/depth/image_raw": "sensor_msgs/msg/Image",
            "/camera/depth/camera_info": "sensor_msgs/msg/CameraInfo"}
        messages = [(c.topic, t, reader.deserialize(raw, c.msgtype))
                    for c, t, raw in reader.messages()]
    images = [m for topic, _, m in messages if topic == DEPTH]
    infos = [m for topic, _, m in messages if topic == INFO]
    assert len(images) == len(infos) == 3
    for image, info, original in zip(images, infos, originals, strict=True):
        assert (image.encoding, image.is_bigendian, image.step) == ("16UC1", 0, 1280)
        assert image.header.frame_id == info.header.frame_id == "camera_depth_optical_frame"
        stamp_us = image.header.stamp.sec * 1_000_000 + image.header.stamp.nanosec // 1000
        offset = stamp_us - original.timestamp_us if offset is None else offset
        assert stamp_us == original.timestamp_us + offset
        assert image.header.stamp == info.header.stamp
        np.testing.assert_array_equal(image.data.view("<u2").reshape(480, 640), original.depth)
        cam = original.intrinsics
        np.testing.assert_allclose(info.k, [cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1])
        assert info.distortion_model == "plumb_bob" and not np.any(info.d)
    assert before <= originals[0].timestamp_us + offset <= time.time_ns() // 1000
    log_times = [t for topic, t, _ in messages if topic == DEPTH]
    assert log_times == [(f.timestamp_us + offset) * 1000 for f in originals]
    # and our reader gives the frames back as they were
    frames, camera = read_all(f"rosbag:{out}")
    assert camera == originals[0].intrinsics
    for frame, original in zip(frames, originals, strict=True):
        assert frame.timestamp_us == original.timestamp_us + offset
        np.testing.assert_array_equal(frame.depth, original.depth)


def test_a_bag_recorded_from_a_bag_keeps_its_stamps(tmp_path, depth_frames):
    bag = write_bag(tmp_path / "orig", "ros1", depth_frames)
    with open_depth(f"rosbag:{bag}") as source:
        record(source, tmp_path / "copy", format="rosbag2")
    frames, camera = read_all(f"rosbag:{tmp_path / 'copy'}")
    assert camera == CAMERA
    assert [f.timestamp_us for f in frames] == [(s + 500) // 1000 for s in STAMPS_NS]


def test_a_bag_recorded_from_a_camera_names_it_so_auto_picks_its_profile(tmp_path):
    """``record`` keeps the source's camera in the bag's metadata (custom_data, read back by
    rosbags' own reader), so the bag names it as the camera did and ``auto`` picks its noise
    profile: a RealSense D435's recording (librealsense 2.56's, read by the bag backend)
    copied to a ROS 2 bag is still a D435."""
    from rosbags.rosbag2 import Reader

    from robot_change.noise.profile import resolve_profile

    original = SIM_FIXTURES / "realsense" / "d435_ros1.bag"
    with open_depth(f"rosbag:{original}") as source:
        assert source.info["name"] == "Intel RealSense D435"
        record(source, tmp_path / "copy", format="rosbag2")
    with Reader(tmp_path / "copy") as reader:
        assert reader.storage.metadata.custom == {"camera_name": "Intel RealSense D435",
                                          "camera_serial": "000000000002"}
    with open_depth(f"rosbag:{tmp_path / 'copy'}") as copy:
        assert copy.info == {"name": "Intel RealSense D435", "serial": "000000000002"}
        assert resolve_profile("auto", camera=copy.info["name"]).name == "realsense_d435"
    # a source that names no camera leaves no custom_data, and the bag names none
    with open_depth(f"oni:{SCENE / 'current.oni'}") as source:
        record(source, tmp_path / "anon", format="rosbag2")
    with Reader(tmp_path / "anon") as reader:
        assert not reader.storage.metadata.custom
    with open_depth(f"rosbag:{tmp_path / 'anon'}") as anon:
        assert anon.info == {}


@pytest.mark.parametrize("custom", ["[1, 2]", "{camera_name: 7, camera_serial: ''}",
                                    "not a mapping", "{camera_name: {a: 1}}", "null"])
def test_a_bag_whose_custom_data_is_not_a_camera_reads_and_names_none(tmp_path, depth_frames,
                                                                      custom):
    from hw.rosbag import write_rosbag2

    frames = [DepthFrame(d, k, 1_000 + k * 33_333, CAMERA) for k, d in enumerate(depth_frames)]
    write_rosbag2(tmp_path / "bag", frames, camera={"name": "Intel RealSense D455"})
    meta = tmp_path / "bag" / "metadata.yaml"
    written = "  custom_data:\n    camera_name: Intel RealSense D455\n"
    assert written in meta.read_text()
    meta.write_text(meta.read_text().replace(written, f"  custom_data: {custom}\n"))
    with open_depth(f"rosbag:{tmp_path / 'bag'}") as source:
        assert source.info == {}
        assert len(list(source)) == len(frames)


def test_write_rosbag2_refuses_what_it_must_not_write_and_leaves_nothing(tmp_path, depth_frames):
    from hw.rosbag import write_rosbag2

    frame = DepthFrame(depth_frames[0], 0, 0, CAMERA)
    (tmp_path / "taken").mkdir()
    for path, text in ((tmp_path / "taken", "exists"), (tmp_path / "x.mcap", "is a folder"),
                       (tmp_path / "no" / "bag", "does not exist")):
        with pytest.raises(DepthFileError, match=text):
            write_rosbag2(path, [frame])
    late = DepthFrame(depth_frames[1], -5, 1, CAMERA)
    with pytest.raises(Exception, match="a ROS time is >= 0"):
        write_rosbag2(tmp_path / "bad", [frame, late])
    with pytest.raises(Exception, match="no frames to write"):
        write_rosbag2(tmp_path / "empty", [])
    assert [p.name for p in tmp_path.iterdir()] == ["taken"]


# --- the command line -----------------------------------------------------------------------
def run(*args: str, timeout: float = 300.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "robot_change.cli", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


def test_cli_record_then_capture_and_detect_on_bags(tmp_path, depth_frames):
    reference = write_bag(tmp_path / "reference", "ros1", depth_frames,
                          camera=Intrinsics.openni_default())
    current = tmp_path / "current"
    made = run("record", "--source", str(SCENE / "current.oni"), "--out", str(current))
    assert made.returncode == 0, made.stderr
    assert "wrote 3 frame(s)" in made.stdout and "ROS 2 bag" in made.stdout
    scene = tmp_path / "station.scene.npz"
    captured = run("capture", "--source", f"rosbag:{reference}?topic={DEPTH}", "--frames", "3",
                   "--out", str(scene))
    assert captured.returncode == 0, captured.stderr
    result = run("detect", "--reference", str(scene), "--current", f"rosbag:{current}",
                 "--frames", "3", "--json")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["outcome"] == "changed"
    assert [region["kind"] for region in summary["regions"]] == ["appeared"]


def test_cli_record_format_choices_and_bad_bags_are_one_line_errors(tmp_path):
    for args, text in [
        (["record", "--source", str(SCENE / "current.oni"), "--out", str(tmp_path / "a"),
          "--codec", "16z"], "--codec 16z is not for a rosbag2 recording"),
        (["record", "--source", str(SCENE / "current.oni"), "--out", str(tmp_path / "a.mcap")],
         "a ROS 2 bag is a folder"),
        (["cloud", "--source", f"rosbag:{tmp_path / 'none.bag'}"], "no such file or folder"),
    ]:
        result = run(*args)
        assert result.returncode == 2, result.stderr
        assert text in result.stderr and "Traceback" not in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    (tmp_path / "noise.bag").write_bytes(b"#ROSBAG V2.0\n" + bytes(range(256)) * 8)
    result = run("cloud", "--source", str(tmp_path / "noise.bag"))
    assert result.returncode == 2 and "not a readable ROS bag" in result.stderr
    assert "Traceback" not in result.stderr


def test_a_realsense_ros1_recording_reads_without_librealsense():
    """librealsense before 2.58 recorded a ROS 1 .bag: mono16 depth (with 4 bytes of slack
    after each Image that rosbags refuses), the CameraInfo under info/, 'Brown Conrady' with
    zero coefficients; written by librealsense 2.56 itself (sim_fixtures/realsense)."""
    folder = SIM_FIXTURES / "realsense"
    with open_depth(str(folder / "d435_ros1.bag")) as source:
        frames = list(source)
        assert source.topic == "/device_0/sensor_0/Depth_0/image/data"
        assert source.intrinsics == Intrinsics(64, 48, 57.6, 57.6, 31.5, 23.5)
    expected = np.load(folder / "d435_ros1.npy")
    assert len(frames) == len(expected)
    assert all(np.array_equal(f.depth, d) for f, d in zip(frames, expected, strict=True))
    assert [f.index for f in frames] == list(range(len(expected)))
