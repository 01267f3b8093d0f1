"""hw.depth: intrinsics, frames, URI parsing and backend choice."""

from __future__ import annotations

import numpy as np
import pytest

from hw import errors
from hw.depth import DepthFrame, Intrinsics, open_depth, parse_uri


def test_openni_default_is_the_nominal_vga_camera():
    k = Intrinsics.openni_default()
    assert (k.width, k.height, k.fx, k.fy, k.cx, k.cy) == (640, 480, 525.0, 525.0, 319.5, 239.5)


def test_scaled_keeps_the_field_of_view():
    k = Intrinsics.openni_default(320, 240)
    assert (k.fx, k.fy) == (262.5, 262.5)
    assert (k.cx, k.cy) == (159.5, 119.5)
    back = k.scaled(640, 480)
    assert back == Intrinsics.openni_default()


def test_parse_reads_four_numbers():
    k = Intrinsics.parse("525,525,320,240")
    assert (k.fx, k.cx, k.width) == (525.0, 320.0, 640)
    with pytest.raises(errors.FrameError, match="fx,fy,cx,cy"):
        Intrinsics.parse("525,525")


@pytest.mark.parametrize(
    "fields, complaint",
    [
        ({"fx": 0.0}, "focal length"),
        ({"fy": float("nan")}, "focal length"),
        ({"cx": float("inf")}, "principal point"),
        ({"cy": 5000.0}, "principal point"),
        ({"width": 0}, "width"),
        ({"height": 2.5}, "height"),
        ({"fx": "525"}, "fx='525': must be a number"),  # was kept as text, failed in a kernel
        ({"cy": True}, "must be a number"),
    ],
)
def test_intrinsics_that_make_no_sense_are_refused(fields, complaint):
    values = dict(width=640, height=480, fx=525.0, fy=525.0, cx=319.5, cy=239.5) | fields
    with pytest.raises(errors.FrameError, match=complaint):
        Intrinsics(**values)


def test_intrinsics_keep_their_numbers_as_floats():
    k = Intrinsics(640, 480, np.float32(612.5), 612, np.float64(321.25), 238)
    assert all(type(getattr(k, n)) is float for n in ("fx", "fy", "cx", "cy"))
    assert k == Intrinsics(640, 480, 612.5, 612.0, 321.25, 238.0)


def test_frame_checks_dtype_shape_and_intrinsics():
    k = Intrinsics.openni_default()
    frame = DepthFrame(np.zeros((480, 640), np.uint16), 0, 0, k)
    assert frame.shape == (480, 640)
    assert frame.valid_fraction() == 0.0
    with pytest.raises(errors.FrameError, match="uint16"):
        DepthFrame(np.zeros((480, 640), np.float32), 0, 0, k)
    with pytest.raises(errors.FrameError, match="uint16"):
        DepthFrame(np.zeros((480, 640, 3), np.uint16), 0, 0, k)
    with pytest.raises(errors.FrameError, match="320x240"):
        DepthFrame(np.zeros((240, 320), np.uint16), 0, 0, k)


@pytest.mark.parametrize(
    "uri, scheme, target, options",
    [
        ("openni2://", "openni2", "", {}),
        ("openni2://1d27/0601@3/4", "openni2", "1d27/0601@3/4", {}),
        ("oni:rec/a.oni", "oni", "rec/a.oni", {}),
        ("rec/a.ONI", "oni", "rec/a.ONI", {}),
        ("images:tum/depth?scale=5000&rate=30", "images", "tum/depth",
         {"scale": "5000", "rate": "30"}),
        ("frames/x.png", "images", "frames/x.png", {}),
        ("frames/x.tiff", "images", "frames/x.tiff", {}),
    ],
)
def test_parse_uri(uri, scheme, target, options):
    assert parse_uri(uri) == (scheme, target, options)


def test_a_folder_means_images(tmp_path):
    assert parse_uri(str(tmp_path))[0] == "images"


@pytest.mark.parametrize("uri", ["", "   ", "kinect://0", "video:foo.avi", "oni:", "images:"])
def test_bad_uris_name_the_known_schemes(uri):
    with pytest.raises(errors.UriError) as info:
        open_depth(uri)
    assert ("openni2" in str(info.value) or "needs a path" in str(info.value)
            or "expected" in str(info.value))


def test_an_existing_file_with_an_unknown_ending_is_refused(tmp_path):
    path = tmp_path / "frame.raw"
    path.write_bytes(b"\0" * 16)
    with pytest.raises(errors.UriError, match="oni:|images:"):
        parse_uri(str(path))


def test_errors_are_one_hierarchy():
    for name in ("UriError", "BackendUnavailable", "DepthFileError", "FrameError", "DeviceError",
                 "DeviceNotFound", "DeviceLost", "FrameTimeout", "PortError"):
        assert issubclass(getattr(errors, name), errors.HwError)
    assert issubclass(errors.DeviceLost, errors.DeviceError)
    assert issubclass(errors.FrameTimeout, TimeoutError)
