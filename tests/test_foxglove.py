"""robot_change.export: a check as Foxglove messages, in an MCAP file and over the live
WebSocket server.  Every file is read back with the mcap library's reader and every protobuf
message decoded with mcap-protobuf-support from the schema the file (or the server) carries;
the decoded contents are compared with the ChangeSet and the scenes they came from."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import REPO, SIM_FIXTURES

pytest.importorskip("foxglove", reason="foxglove-sdk (the viz extra) is not installed")
mcap_reader = pytest.importorskip("mcap.reader", reason="mcap (the test extra) is not installed")
pytest.importorskip("mcap_protobuf", reason="mcap-protobuf-support (the test extra) is missing")
pytest.importorskip("websockets", reason="websockets (the test extra) is not installed")

from foxglove_client import FoxgloveClient, mcap_decoders  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

import sim_fixtures  # noqa: E402
from hw.oni import read_oni_frames  # noqa: E402
from robot_change.change.detect import detect_changes  # noqa: E402
from robot_change.change.mount import CameraMount  # noqa: E402
from robot_change.change.registration import invert, transform_points  # noqa: E402
from robot_change.change.scene import build_scene  # noqa: E402
from robot_change.export.foxglove import (  # noqa: E402
    FRAMES,
    POINT_DTYPE,
    REPORT_SCHEMA_NAME,
    SIGMAS,
    TOPICS,
    check_messages,
)
from robot_change.export.live import LiveView  # noqa: E402
from robot_change.export.mcap import CheckFileWriter  # noqa: E402

MOUNT = CameraMount((0.2, 0.05, 0.5), (0.0, 10.0, 5.0))
STAMP = 1_796_000_000_123_456_789
#: removed and added objects, the robot 5 cm off its station pose: both kinds of region and a
#: registration that is not the identity
SCENE = "lab_two_changes_pose_5cm"


@pytest.fixture(scope="module")
def check():
    scene = sim_fixtures.load_scene(SCENE)
    reference = build_scene(read_oni_frames(str(scene.reference_oni))[:3])
    depth = read_oni_frames(str(scene.current_oni))[0].depth
    changes = detect_changes(reference, depth)
    assert changes.appeared and changes.disappeared
    assert np.linalg.norm(changes.registration.translation_m) > 0.02
    return reference, depth, changes


@pytest.fixture(scope="module")
def written(check, tmp_path_factory):
    """The check written to an MCAP file, read back: (path, header, summary, metadata,
    topic -> (channel, schema, message, decoded))."""
    reference, depth, changes = check
    report = {**changes.summary(MOUNT), "station": "lab"}
    path = tmp_path_factory.mktemp("mcap") / "check.mcap"
    messages = check_messages(reference, depth, changes, MOUNT, report=report, stamp_ns=STAMP)
    size = CheckFileWriter().write(path, messages, STAMP, {"station": "lab"})
    assert size == path.stat().st_size
    with open(path, "rb") as f:
        reader = mcap_reader.make_reader(f, decoder_factories=mcap_decoders())
        header, summary = reader.get_header(), reader.get_summary()
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        got: dict[str, list] = {}
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            got.setdefault(channel.topic, []).append((channel, schema, message, decoded))
    return path, header, summary, metadata, got


def matrix(transform) -> np.ndarray:
    """(4, 4) of a decoded foxglove.FrameTransform (or Pose): the child's pose in the parent."""
    q = transform.rotation if hasattr(transform, "rotation") else transform.orientation
    t = transform.translation if hasattr(transform, "translation") else transform.position
    out = np.eye(4)
    out[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    out[:3, 3] = [t.x, t.y, t.z]
    return out


def cloud_of(decoded) -> np.ndarray:
    """The packed points of a decoded foxglove.PointCloud as POINT_DTYPE records."""
    assert decoded.point_stride == POINT_DTYPE.itemsize
    names = [(f.name, f.offset) for f in decoded.fields]
    assert names == [(n, POINT_DTYPE.fields[n][1]) for n in POINT_DTYPE.names]
    return np.frombuffer(decoded.data, POINT_DTYPE)


def xyz(records: np.ndarray) -> np.ndarray:
    return np.stack([records["x"], records["y"], records["z"]], axis=1)


# ---------------------------------------------------------------------------------------------
# the MCAP file


def test_one_message_per_topic_with_foxglove_schemas_and_the_check_time(written):
    _path, header, summary, metadata, got = written
    assert "foxglove-sdk" in header.library
    assert set(got) == set(TOPICS)
    assert summary.statistics.message_count == len(TOPICS)
    for topic, schema_name in TOPICS.items():
        [(channel, schema, message, _decoded)] = got[topic]
        assert message.log_time == STAMP
        if schema_name == "json":
            assert channel.message_encoding == "json" and schema.name == REPORT_SCHEMA_NAME
        else:
            assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf"
            assert schema.name == f"foxglove.{schema_name}"
    assert metadata == {"robot_change": {"station": "lab"}}


def test_frame_ids_and_stamps_let_foxglove_place_everything(written):
    got = written[4]
    frame_of = {topic: entries[0][3].frame_id for topic, entries in got.items()
                if hasattr(entries[0][3], "frame_id")}
    assert frame_of == {
        "/current/depth/image": "camera_optical", "/current/depth/camera_info": "camera_optical",
        "/reference/depth/image": "reference_camera_optical",
        "/reference/depth/camera_info": "reference_camera_optical",
        "/current/cloud": "camera_optical", "/reference/cloud": "reference_camera_optical",
        "/change/appeared": "camera_optical", "/change/disappeared": "camera_optical"}
    for topic in ("/reference/mixture", "/change/novelty", "/change/regions"):
        update = got[topic][0][3]
        assert {e.frame_id for e in update.entities} == (
            {"reference_camera_optical"} if topic == "/reference/mixture" else
            {"camera_optical"})
        # a new check replaces what the previous one showed
        assert [d.type for d in update.deletions] == [1]  # SceneEntityDeletion.ALL
    tree = got["/tf"][0][3].transforms
    assert [(t.parent_frame_id, t.child_frame_id) for t in tree] == list(zip(FRAMES, FRAMES[1:],
                                                                             strict=False))
    stamped = [t.timestamp for t in tree] + [got["/current/cloud"][0][3].timestamp]
    assert {(s.seconds, s.nanos) for s in stamped} == {divmod(STAMP, 1_000_000_000)}


def test_the_transforms_compose_to_the_mount_and_the_registration(check, written):
    reference, _depth, changes = check
    tree = {t.child_frame_id: matrix(t) for t in written[4]["/tf"][0][3].transforms}
    base_from_optical = tree["camera_link"] @ tree["camera_optical"]
    np.testing.assert_allclose(base_from_optical, MOUNT.base_from_optical(), atol=1e-9)
    # the reference's own points, put in place by the tree, are where the check compared them:
    # its disappeared points are reference points moved into the current camera frame
    cur_from_ref = tree["reference_camera_optical"]
    moved = transform_points(cur_from_ref, reference.points[changes.disappeared_index])
    np.testing.assert_allclose(moved, changes.disappeared_points, atol=1e-5)
    # the robot at its station pose, seen from the robot now: the inverse of the offset the
    # report gives in base_link
    base_from_station = base_from_optical @ cur_from_ref @ tree["reference_base_link"]
    offset = MOUNT.offset(changes.registration)
    np.testing.assert_allclose(invert(base_from_station)[:3, 3], offset.translation_m,
                               atol=1e-9)
    np.testing.assert_allclose(Rotation.from_matrix(invert(base_from_station)[:3, :3])
                               .as_euler("ZYX", degrees=True)[::-1], offset.rpy_deg, atol=1e-6)


def test_depth_images_and_calibrations_are_the_check_s(check, written):
    reference, depth, _changes = check
    got = written[4]
    cam = reference.intrinsics
    for topic, image in (("/current/depth/image", depth),
                         ("/reference/depth/image", reference.depth)):
        decoded = got[topic][0][3]
        assert (decoded.width, decoded.height, decoded.encoding, decoded.step) == (
            cam.width, cam.height, "16UC1", 2 * cam.width)
        np.testing.assert_array_equal(
            np.frombuffer(decoded.data, "<u2").reshape(cam.height, cam.width), image)
        info = got[topic.replace("image", "camera_info")][0][3]
        assert (info.width, info.height) == (cam.width, cam.height)
        assert list(info.K) == pytest.approx([cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1])
        assert list(info.P)[:3] == pytest.approx([cam.fx, 0, cam.cx]) and list(info.D) == [0] * 5


def test_the_clouds_hold_the_check_s_points_in_their_colours(check, written):
    reference, _depth, changes = check
    got = written[4]
    current = cloud_of(got["/current/cloud"][0][3])
    np.testing.assert_array_equal(xyz(current), changes.current_points)
    np.testing.assert_array_equal(xyz(current)[changes.appeared_index], changes.appeared_points)
    np.testing.assert_array_equal(xyz(cloud_of(got["/reference/cloud"][0][3])), reference.points)
    appeared = cloud_of(got["/change/appeared"][0][3])
    disappeared = cloud_of(got["/change/disappeared"][0][3])
    np.testing.assert_array_equal(xyz(appeared), changes.appeared_points)
    np.testing.assert_array_equal(xyz(disappeared), changes.disappeared_points)
    assert (appeared["green"] > 200).all() and (appeared["red"] < 60).all()
    assert (disappeared["red"] > 200).all() and (disappeared["green"] < 60).all()
    assert (appeared["alpha"] == 255).all()


def covariance_of(sphere) -> np.ndarray:
    """The covariance an ellipsoid stands for: SIGMAS standard deviations out along its
    axes."""
    T = matrix(sphere.pose)
    sd = np.array([sphere.size.x, sphere.size.y, sphere.size.z]) / (2 * SIGMAS)
    return T[:3, :3] @ np.diag(sd ** 2) @ T[:3, :3].T


def test_the_reference_mixture_as_3_sigma_ellipsoids_coloured_by_weight(check, written):
    reference, _depth, _changes = check
    mixture = reference.mixture
    entities = written[4]["/reference/mixture"][0][3].entities
    assert len(entities) == mixture.n_components
    reds = []
    for k, entity in enumerate(entities):
        [sphere] = entity.spheres
        np.testing.assert_allclose(matrix(sphere.pose)[:3, 3], mixture.means[k], atol=1e-9)
        np.testing.assert_allclose(covariance_of(sphere), mixture.covariances[k], atol=1e-9)
        assert 0 < sphere.color.a < 1
        assert {m.key: m.value for m in entity.metadata}["weight"] == \
            f"{mixture.weights[k]:.4f}"
        reds.append(sphere.color.r)
    # the heavier the component, the warmer its colour
    order = np.argsort(mixture.weights)
    assert np.all(np.diff(np.asarray(reds)[order]) >= -1e-9)


def test_novelty_components_and_the_accepted_change(check, written):
    _reference, _depth, changes = check
    entities = {e.id: e for e in written[4]["/change/novelty"][0][3].entities}
    expected = ([f"appeared_novelty_{k}" for k in changes.greedy_appeared.candidates]
                + [f"disappeared_novelty_{k}" for k in changes.greedy_disappeared.candidates])
    assert list(entities) == expected
    for kind, mixture, trace in (("appeared", changes.appeared_mixture, changes.greedy_appeared),
                                 ("disappeared", changes.disappeared_mixture,
                                  changes.greedy_disappeared)):
        for k in trace.candidates:
            [sphere] = entities[f"{kind}_novelty_{k}"].spheres
            np.testing.assert_allclose(covariance_of(sphere), mixture.covariances[k], atol=1e-9)
            assert (sphere.color.a > 0.3) == (k in trace.change)


def test_region_boxes_with_labels(check, written):
    _reference, _depth, changes = check
    entities = written[4]["/change/regions"][0][3].entities
    assert len(entities) == len(changes.regions)
    for number, (entity, region) in enumerate(zip(entities, changes.regions, strict=True), 1):
        [cube], [text] = entity.cubes, entity.texts
        np.testing.assert_allclose(matrix(cube.pose)[:3, 3],
                                   (region.bbox_min + region.bbox_max) / 2, atol=1e-6)
        np.testing.assert_allclose([cube.size.x, cube.size.y, cube.size.z], region.extent,
                                   atol=1e-6)
        assert text.text.startswith(f"{region.kind} {number}: {region.n_points} points, ")
        distance = float(np.linalg.norm(region.centroid))
        assert text.text.endswith(f"{distance:.2f} m away")
        assert (cube.color.g > cube.color.r) == (region.kind == "appeared")


def test_the_report_is_the_summary_and_the_log_says_the_outcome(check, written):
    _reference, _depth, changes = check
    got = written[4]
    report = json.loads(got["/check/report"][0][2].data)
    assert report == json.loads(json.dumps({**changes.summary(MOUNT), "station": "lab"}))
    log = got["/check/log"][0][3]
    assert log.message.startswith("lab: changed;") and log.level == 3  # WARNING
    assert "; appeared 1: " in log.message and "; disappeared " in log.message


# ---------------------------------------------------------------------------------------------
# writing


def test_a_failed_write_leaves_the_old_file_and_no_temp_file(check, tmp_path):
    reference, depth, changes = check
    path = tmp_path / "check.mcap"
    writer = CheckFileWriter()
    messages = check_messages(reference, depth, changes, stamp_ns=STAMP)
    writer.write(path, messages, STAMP)
    before = path.read_bytes()
    broken = [(t, {"bad": object()} if t == "/check/report" else m) for t, m in messages]
    with pytest.raises(TypeError):
        writer.write(path, broken, STAMP)
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == [
        "check.mcap"]
    # the writer goes on writing after a failure
    writer.write(tmp_path / "again.mcap", messages, STAMP + 1)
    with open(tmp_path / "again.mcap", "rb") as f:
        assert mcap_reader.make_reader(f).get_summary().statistics.message_count == len(TOPICS)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        writer.write(tmp_path / "absent" / "x.mcap", messages, STAMP)


def test_a_current_image_of_another_size_is_refused(check):
    reference, depth, changes = check
    from robot_change.errors import InputError

    with pytest.raises(InputError, match="uint16 image like the reference's"):
        check_messages(reference, depth[::2], changes)


# ---------------------------------------------------------------------------------------------
# the live view


def test_the_live_view_serves_every_topic_and_latches_the_last_check(check):
    reference, depth, changes = check
    messages = check_messages(reference, depth, changes, MOUNT, stamp_ns=STAMP)
    view = LiveView("127.0.0.1", 0)
    try:
        assert view.port > 0
        with FoxgloveClient("127.0.0.1", view.port) as client:
            client.wait_for_channels(set(TOPICS))
            assert {c["topic"]: c["schemaName"] for c in client.channels.values()} == {
                t: REPORT_SCHEMA_NAME if s == "json" else f"foxglove.{s}"
                for t, s in TOPICS.items()}
            client.subscribe_all()
            view.publish(messages, STAMP)
            got = client.receive(set(TOPICS))
        assert {stamp for stamp, _d, _p in got.values()} == {STAMP}
        np.testing.assert_array_equal(xyz(cloud_of(got["/change/appeared"][1])),
                                      changes.appeared_points)
        assert got["/check/report"][1] == json.loads(json.dumps(changes.summary(MOUNT)))
        assert len(got["/reference/mixture"][1].entities) == reference.mixture.n_components
        # a viewer that comes after the check still sees it
        with FoxgloveClient("127.0.0.1", view.port) as late:
            late.wait_for_channels(set(TOPICS))
            late.subscribe_all()
            again = late.receive(set(TOPICS))
        assert {t: p for t, (_s, _d, p) in again.items()} == {
            t: p for t, (_s, _d, p) in got.items()}
    finally:
        view.close()


def test_a_taken_port_is_an_error_from_the_server():
    first = LiveView("127.0.0.1", 0)
    try:
        with pytest.raises(Exception):  # noqa: B017 -- whatever the SDK raises, it is raised
            LiveView("127.0.0.1", first.port)
    finally:
        first.close()


# ---------------------------------------------------------------------------------------------
# the command line


def run(*args: str, code: str = "", timeout: float = 120.0) -> subprocess.CompletedProcess:
    """``robot-change ARGS`` in a subprocess, after ``code`` (Python) has run."""
    program = f"{code}\nimport sys\nfrom robot_change.cli import main\nsys.exit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", program, *args], cwd=REPO, capture_output=True,
                          text=True, timeout=timeout)


def test_detect_mcap_writes_the_check_beside_report_json(tmp_path):
    scene = SIM_FIXTURES / "scenes" / "office_box_added"
    result = run("detect", "--reference", str(scene / "reference.oni"), "--current",
                 str(scene / "current.oni"), "--out", str(tmp_path), "--no-picture",
                 "--mount", "0.2,0,0.5,0,10,0", "--mcap", str(tmp_path / "check.mcap"))
    assert result.returncode == 0, result.stderr
    assert f"wrote {tmp_path / 'check.mcap'}" in result.stdout
    report = json.loads((tmp_path / "report.json").read_text())
    assert str(tmp_path / "check.mcap") in report["files"]
    with open(tmp_path / "check.mcap", "rb") as f:
        reader = mcap_reader.make_reader(f, decoder_factories=mcap_decoders())
        got = {channel.topic: (message, decoded)
               for _s, channel, message, decoded in reader.iter_decoded_messages()}
    assert set(got) == set(TOPICS)
    assert json.loads(got["/check/report"][0].data) == report
    appeared = xyz(cloud_of(got["/change/appeared"][1]))
    np.testing.assert_array_equal(appeared, np.load(tmp_path / "appeared.npy"))
    tree = {t.child_frame_id: matrix(t) for t in got["/tf"][1].transforms}
    np.testing.assert_allclose(tree["camera_link"] @ tree["camera_optical"],
                               CameraMount.parse("0.2,0,0.5,0,10,0").base_from_optical(),
                               atol=1e-9)


def test_detect_mcap_without_foxglove_sdk_is_one_clear_line_before_any_work(tmp_path):
    scene = SIM_FIXTURES / "scenes" / "office_box_added"
    result = run("detect", "--reference", str(scene / "reference.oni"), "--current",
                 str(scene / "current.oni"), "--mcap", str(tmp_path / "check.mcap"),
                 code="import sys; sys.modules['foxglove'] = None  # as if not installed")
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines()[-1] == (
        "robot-change detect: error: Foxglove views of a check need foxglove-sdk: install the "
        "'viz' extra (./setup.sh viz, or pip install 'robot-change[viz]')")
    assert "Traceback" not in result.stderr and not (tmp_path / "check.mcap").exists()
    assert "ended after" not in result.stderr  # refused before reading any depth


def test_ellipsoid_axes_is_the_covariance_s_eigen_decomposition():
    from robot_change.export.foxglove import ellipsoid_axes

    rng = np.random.default_rng(3)
    for _ in range(20):
        a = rng.normal(size=(3, 3))
        cov = a @ a.T + 1e-4 * np.eye(3)
        size, rotation = ellipsoid_axes(cov)
        assert np.linalg.det(rotation) == pytest.approx(1.0)
        np.testing.assert_allclose(rotation @ np.diag((size / 6) ** 2) @ rotation.T, cov,
                                   atol=1e-12)
    # a degenerate (flat) component: no NaN, a zero axis
    size, _ = ellipsoid_axes(np.diag([1e-2, 1e-2, 0.0]))
    assert np.all(np.isfinite(size)) and size.min() == pytest.approx(0.0, abs=1e-9)


def test_the_topics_are_the_documented_ones():
    text = (REPO / "docs" / "ros.md").read_text()
    for topic in TOPICS:
        assert f"`{topic}`" in text, topic
    for frame in FRAMES:
        assert f"`{frame}`" in text, frame


def test_a_check_not_at_the_station_is_drawn_too(tmp_path):
    """Nothing compared: the clouds, images, frames and the reason, no changed points."""
    scene = sim_fixtures.load_scene("office_far_offset")
    reference = build_scene(read_oni_frames(str(scene.reference_oni))[:3])
    depth = read_oni_frames(str(scene.current_oni))[0].depth
    changes = detect_changes(reference, depth)
    assert changes.outcome == "not_at_station"
    CheckFileWriter().write(tmp_path / "far.mcap", check_messages(
        reference, depth, changes, stamp_ns=STAMP), STAMP)
    with open(tmp_path / "far.mcap", "rb") as f:
        got = {channel.topic: decoded for _s, channel, _m, decoded in mcap_reader.make_reader(
            f, decoder_factories=mcap_decoders()).iter_decoded_messages()}
    assert set(got) == set(TOPICS)
    assert len(cloud_of(got["/change/appeared"])) == 0 == len(got["/change/regions"].entities)
    assert len(got["/change/novelty"].entities) == 0
    np.testing.assert_array_equal(xyz(cloud_of(got["/current/cloud"])), changes.current_points)
    assert got["/check/report"]["outcome"] == "not_at_station"
    assert changes.not_at_station_reason in got["/check/log"].message
