"""hw.images: depth images and folders of them as a DepthSource (the ``images:`` backend)."""

from __future__ import annotations

import io
import time

import numpy as np
import pytest
from PIL import Image

from hw import errors
from hw.depth import Intrinsics, open_depth
from hw.imagefile import write_png
from hw.images import (
    ImageFolderSource,
    depth_named,
    natural_key,
    open_images,
    read_depth_image,
    stem_timestamp_us,
    to_millimetres,
)

RNG = np.random.default_rng(3)


def depth_image(shape=(6, 8), base=900):
    """Millimetres a depth camera reads (base + 0..5999, wrapping on large images)."""
    depth = (base + np.arange(shape[0] * shape[1]).reshape(shape) % 6000).astype(np.uint16)
    depth[0, 0] = 0
    return depth


def make_folder(folder, names, shape=(6, 8)):
    """Write one depth PNG per name (value base = 1000 * position), return the arrays."""
    folder.mkdir(exist_ok=True)
    arrays = {}
    for position, name in enumerate(names):
        arrays[name] = depth_image(shape, base=1000 * (position + 1))
        write_png(folder / name, arrays[name])
    return arrays


# ----------------------------------------------------------------- read_depth_image


def test_millimetres_pass_through_unchanged(tmp_path):
    depth = RNG.integers(0, 65535, size=(5, 7), dtype=np.uint16, endpoint=True)
    write_png(tmp_path / "d.png", depth)
    np.testing.assert_array_equal(read_depth_image(tmp_path / "d.png"), depth)


def test_scale_converts_with_rounding_and_saturation():
    raw = np.array([[0, 1, 2, 3, 12, 13, 5000, 65535]], dtype=np.uint16)
    np.testing.assert_array_equal(to_millimetres(raw, 5000.0),
                                  [[0, 0, 0, 1, 2, 3, 1000, 13107]])
    # half up: 1 raw unit at 2000 per metre is 0.5 mm -> 1 mm
    np.testing.assert_array_equal(to_millimetres(np.array([[1, 3]], np.uint16), 2000.0), [[1, 2]])
    # 100 units per metre: 10 mm each, saturating at 65535
    np.testing.assert_array_equal(to_millimetres(np.array([[0, 6553, 6554, 65535]], np.uint16),
                                                 100.0), [[0, 65530, 65535, 65535]])
    assert to_millimetres(raw, 5000.0).dtype == np.uint16


def test_format_is_told_by_content_not_name(tmp_path):
    depth = depth_image()
    buffer = io.BytesIO()
    Image.fromarray(depth).save(buffer, format="TIFF", compression="tiff_lzw")
    (tmp_path / "really_a_tiff.png").write_bytes(buffer.getvalue())
    np.testing.assert_array_equal(read_depth_image(tmp_path / "really_a_tiff.png"), depth)


def test_eight_bit_images_are_not_depth(tmp_path):
    write_png(tmp_path / "gray.png", np.zeros((4, 4), np.uint8))
    with pytest.raises(errors.DepthFileError, match=r"gray\.png: 8-bit grayscale image is not "
                                                    "a depth image"):
        read_depth_image(tmp_path / "gray.png")


@pytest.mark.parametrize("content, complaint", [(b"", "empty"),
                                                (b"P5\n4 4\n255\n" + bytes(16), "neither")])
def test_other_files_are_refused(tmp_path, content, complaint):
    (tmp_path / "x.png").write_bytes(content)
    with pytest.raises(errors.DepthFileError, match=complaint):
        read_depth_image(tmp_path / "x.png")


def test_real_tum_png_at_scale_5000(shared_data):
    path = shared_data / "open3d-tum-sample" / "TUM_depth.png"
    raw = np.array(Image.open(path)).astype(np.int64)
    expected = (2 * raw + 5) // 10  # raw / 5 mm, rounded half up, in integers
    depth = read_depth_image(path, scale=5000)
    np.testing.assert_array_equal(depth, expected)
    valid = depth[depth > 0]
    assert 1000 < np.median(valid) < 4000  # an office desk, 1-4 m away


# -------------------------------------------------------------- names, order, times


def test_natural_order():
    names = ["frame_10.png", "frame_2.png", "Frame_1.png", "frame_100.png", "frame_9.tif"]
    assert sorted(names, key=natural_key) == ["Frame_1.png", "frame_2.png", "frame_9.tif",
                                              "frame_10.png", "frame_100.png"]


@pytest.mark.parametrize("stem, micros", [
    ("1305031102.160407", 1305031102160407),
    ("1305031102.1604075", 1305031102160408),  # rounded to the microsecond
    ("12.5", 12_500_000),
    ("frame_20121214T142255.814212_depth", 1355494975814212),
    ("20121214T142256", 1355494976000000),
    ("000123", None),  # a frame number, not a time
    ("frame_0001", None),
    ("1.2.3", None),
])
def test_timestamps_from_file_names(stem, micros):
    assert stem_timestamp_us(stem) == micros


# ------------------------------------------------------------------- the source


def test_folder_delivers_frames_in_natural_order(tmp_path):
    names = ["frame_10.png", "frame_2.png", "frame_1.png"]
    arrays = make_folder(tmp_path / "seq", names)
    (tmp_path / "seq" / "notes.txt").write_text("not an image")
    with open_images(str(tmp_path / "seq")) as source:
        frames = list(source)
        assert source.read() is None  # stays at the end
        assert source.stats.delivered == 3
    assert [f.index for f in frames] == [0, 1, 2]
    assert [f.timestamp_us for f in frames] == [0, 33333, 66666]
    for frame, name in zip(frames, ["frame_1.png", "frame_2.png", "frame_10.png"], strict=True):
        np.testing.assert_array_equal(frame.depth, arrays[name])
        assert frame.intrinsics == Intrinsics.openni_default(8, 6)


def test_tum_names_give_timestamps_and_time_order(tmp_path):
    names = ["1305031102.5.png", "1305031102.25.png", "1305031103.0.png"]
    arrays = make_folder(tmp_path / "tum", names)
    with open_images(str(tmp_path / "tum")) as source:
        frames = list(source)
    assert [f.timestamp_us for f in frames] == [1305031102250000, 1305031102500000,
                                                1305031103000000]
    np.testing.assert_array_equal(frames[0].depth, arrays["1305031102.25.png"])


def test_loop_repeats_with_increasing_index_and_time(tmp_path):
    arrays = make_folder(tmp_path / "tum", ["100.0.png", "100.5.png"])
    with open_images(str(tmp_path / "tum"), loop="1") as source:
        frames = [source.read() for _ in range(5)]
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    assert [f.timestamp_us for f in frames] == [100_000_000, 100_500_000, 101_000_000,
                                                101_500_000, 102_000_000]
    np.testing.assert_array_equal(frames[4].depth, arrays["100.0.png"])
    np.testing.assert_array_equal(frames[3].depth, arrays["100.5.png"])


def test_a_single_file_is_a_one_frame_source(tmp_path):
    arrays = make_folder(tmp_path, ["only.png"])
    with open_images(str(tmp_path / "only.png")) as source:
        frame = source.read()
        assert source.read() is None
    np.testing.assert_array_equal(frame.depth, arrays["only.png"])


def test_rate_paces_delivery(tmp_path):
    make_folder(tmp_path / "seq", ["a.png"])
    with open_images(str(tmp_path / "seq"), rate="50", loop=True) as source:
        start = time.monotonic()
        for _ in range(5):
            source.read()
        elapsed = time.monotonic() - start
    assert elapsed >= 0.07  # 4 periods of 20 ms after the first frame


def test_a_frame_not_due_within_the_timeout_is_a_frame_timeout(tmp_path):
    make_folder(tmp_path / "seq", ["a.png", "b.png"])
    with open_images(str(tmp_path / "seq"), rate=2) as source:
        assert source.read().index == 0
        with pytest.raises(errors.FrameTimeout, match="paced at 2 fps"):
            source.read(timeout=0.01)
        assert source.read(timeout=2.0).index == 1


def test_close_and_open_start_again(tmp_path):
    make_folder(tmp_path / "seq", ["a.png", "b.png"])
    source = open_images(str(tmp_path / "seq"))
    with pytest.raises(errors.DeviceError, match="not open"):
        source.read()
    with source:
        assert source.read().index == 0
        assert source.read().index == 1
    with source:
        assert source.read().index == 0


def test_intrinsics_default_given_and_as_text(tmp_path):
    make_folder(tmp_path / "seq", ["a.png"], shape=(240, 320))
    folder = str(tmp_path / "seq")
    assert open_images(folder).intrinsics == Intrinsics.openni_default(320, 240)
    given = Intrinsics(320, 240, 300.0, 301.0, 160.0, 120.0)
    with open_images(folder, intrinsics=given) as source:
        assert source.read().intrinsics is given
    with open_depth(f"images:{folder}?intrinsics=300,301,160,120") as source:
        assert source.read().intrinsics == given
    with pytest.raises(errors.FrameError, match="intrinsics given are for 640x480"):
        open_images(folder, intrinsics=Intrinsics.openni_default()).open()


def test_mixed_sizes_are_refused_naming_the_file(tmp_path):
    make_folder(tmp_path / "seq", ["1.png", "3.png"])
    write_png(tmp_path / "seq" / "2.png", depth_image((7, 8)))
    with open_images(str(tmp_path / "seq")) as source:
        assert source.read().index == 0
        with pytest.raises(errors.FrameError, match=r"2\.png: is 8x7 but 1\.png is 8x6"):
            source.read()
        assert source.read().index == 2  # moves on; the bad file counts as dropped
        assert (source.stats.delivered, source.stats.dropped) == (2, 1)


def test_corrupt_file_in_a_folder_is_named_and_skipped(tmp_path):
    make_folder(tmp_path / "seq", ["1.png", "3.png"])
    (tmp_path / "seq" / "2.png").write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00")
    with open_images(str(tmp_path / "seq")) as source:
        source.read()
        with pytest.raises(errors.DepthFileError, match=r"2\.png: truncated or corrupt PNG"):
            source.read()
        assert source.read().index == 2


def test_pattern_and_hidden_files(tmp_path):
    make_folder(tmp_path / "seq", ["a_depth.png", "b_depth.png", "a_label.png",
                                   ".partial_depth.png"])
    with open_images(str(tmp_path / "seq"), pattern="*_depth.png") as source:
        assert len(list(source)) == 2
    with open_images(str(tmp_path / "seq"), pattern="*.png") as source:
        assert len(list(source)) == 3
    with open_images(str(tmp_path / "seq")) as source:  # the files named depth, as below
        assert len(list(source)) == 2


def test_a_folder_of_depth_beside_colour_reads_the_depth(tmp_path):
    """A dataset's frames folder holds colour beside depth (7-Scenes, SUN3D:
    ``frame-N.color.png`` and ``frame-N.depth.png``): the depth ones are read, in order;
    ``pattern=`` still picks what it names (here the colour images, refused as not depth)."""
    folder = tmp_path / "frames"
    folder.mkdir()
    depths = [depth_image(base=900 + 100 * k) for k in range(3)]
    for k, depth in enumerate(depths):
        write_png(folder / f"frame-{k:06d}.depth.png", depth)
        Image.fromarray(np.zeros((6, 8, 3), np.uint8)).save(folder / f"frame-{k:06d}.color.png")
        (folder / f"frame-{k:06d}.pose.txt").write_text("1 0 0 0\n")
    with open_depth(str(folder)) as source:
        frames = list(source)
    assert [f.depth.tolist() for f in frames] == [d.tolist() for d in depths]
    with pytest.raises(errors.NotDepthImageError, match="RGB PNG is not a depth image"):
        with open_depth(f"images:{folder}?pattern=*.color.png") as source:
            list(source)
    assert depth_named([folder / "a.png", folder / "b.png"]) == [folder / "a.png",
                                                                 folder / "b.png"]


def test_a_folder_mixing_depth_with_unnamed_others_names_pattern(tmp_path):
    """Depth frames beside colour ones, neither named depth: the first colour file stops the
    folder with the typed error and the option that picks the depth ones; one colour file
    alone gets the error without it."""
    folder = tmp_path / "frames"
    folder.mkdir()
    write_png(folder / "0001_d.png", depth_image())
    Image.fromarray(np.zeros((6, 8, 3), np.uint8)).save(folder / "0001_rgb.png")
    with pytest.raises(errors.NotDepthImageError, match=r"RGB PNG .*\?pattern="):
        with open_depth(str(folder)) as source:
            list(source)
    with open_depth(f"images:{folder}?pattern=*_d.png") as source:
        assert len(list(source)) == 1
    with pytest.raises(errors.NotDepthImageError, match="RGB PNG is not a depth image") as info:
        open_depth(str(folder / "0001_rgb.png")).open()
    assert "pattern" not in str(info.value)


# --------------------------------------------------------------------- bad input


def test_missing_target(tmp_path):
    with pytest.raises(errors.DepthFileError, match="no such file or folder"):
        open_images(str(tmp_path / "nowhere"))
    with pytest.raises(errors.DepthFileError, match="no such file or folder"):
        open_depth(str(tmp_path / "nowhere.png"))


def test_folder_without_images_says_what_it_looked_for(tmp_path):
    (tmp_path / "readme.txt").write_text("x")
    with pytest.raises(errors.DepthFileError, match=r"no depth images .*\*\.png, \*\.tif, "
                                                    r"\*\.tiff"):
        open_depth(f"images:{tmp_path}")
    make_folder(tmp_path, ["a.png"])
    with pytest.raises(errors.DepthFileError, match="matching '\\*_depth.png'"):
        open_images(str(tmp_path), pattern="*_depth.png")
    # a dataset's top folder: its clouds, or its depth folder, named
    top = tmp_path / "dataset"
    (top / "depth").mkdir(parents=True)
    (top / "view1.pcd").write_text("# .PCD v0.7\n")
    with pytest.raises(errors.DepthFileError, match=f"pcd:{top}; its folder 'depth' may hold"):
        open_depth(str(top))


@pytest.mark.parametrize("query, complaint", [
    ("scale=abc", "scale='abc': expected a number > 0"),
    ("scale=0", "scale='0'"),
    ("scale=-5000", "scale='-5000'"),
    ("scale=nan", "scale='nan'"),
    ("rate=0", "rate='0': expected a number > 0"),
    ("rate=fast", "rate='fast'"),
    ("loop=maybe", "loop='maybe': expected 1 or 0"),
    ("intrinsics=525,525,319.5", "intrinsics='525,525,319.5': expected four numbers"),
    ("scal=5000", "scal unknown; the images backend takes scale"),
])
def test_bad_uri_options_are_uri_errors(tmp_path, query, complaint):
    make_folder(tmp_path, ["a.png"])
    with pytest.raises(errors.UriError, match=complaint):
        open_depth(f"images:{tmp_path}?{query}")


def test_bad_keyword_options_are_uri_errors(tmp_path):
    make_folder(tmp_path, ["a.png"])
    with pytest.raises(errors.UriError, match="loop=2"):
        open_images(str(tmp_path), loop=2)
    with pytest.raises(errors.UriError, match="intrinsics=525"):
        open_images(str(tmp_path), intrinsics=525)


# ------------------------------------------------------------------ end to end


def test_open_depth_end_to_end_with_uri_options(tmp_path):
    raw = {"1.0.png": np.full((4, 5), 5000, np.uint16), "1.1.png": np.full((4, 5), 7501,
                                                                           np.uint16)}
    (tmp_path / "tum").mkdir()
    for name, array in raw.items():
        write_png(tmp_path / "tum" / name, array)
    source = open_depth(f"images:{tmp_path / 'tum'}?scale=5000&loop=0")
    assert isinstance(source, ImageFolderSource)
    assert source.uri.startswith("images:")
    with source:
        frames = list(source)
    assert [int(f.depth[0, 0]) for f in frames] == [1000, 1500]
    assert [f.timestamp_us for f in frames] == [1_000_000, 1_100_000]
    with open_depth(str(tmp_path / "tum"), scale=5000) as bare:  # a bare folder path
        assert len(list(bare)) == 2


def test_real_pcl_grabber_folder(shared_data):
    folder = shared_data / "pcl-grabber-seq"
    with open_depth(f"images:{folder}?pattern=*_depth.tiff") as source:
        frames = list(source)
    paths = sorted(folder.glob("*_depth.tiff"))
    assert len(frames) == 3
    for frame, path in zip(frames, paths, strict=True):
        np.testing.assert_array_equal(frame.depth, np.array(Image.open(path)))
    gaps = np.diff([f.timestamp_us for f in frames])
    assert np.all((gaps > 200_000) & (gaps < 300_000))  # frames ~0.25 s apart
    with open_depth(f"images:{folder}") as source:  # without a pattern: the depth ones too
        assert [f.depth.tolist() for f in source] == [f.depth.tolist() for f in frames]
    with pytest.raises(errors.DepthFileError, match="RGB TIFF"):  # rgb files named
        with open_depth(f"images:{folder}?pattern=*.tiff") as source:
            list(source)


def test_real_osd_tabletop_folder(shared_data):
    folder = shared_data / "osd-tabletop" / "derived"
    with open_depth(f"images:{folder}?pattern=*_depth_mm.png") as source:
        frames = list(source)
    assert len(frames) == 13
    assert all(f.shape == (480, 640) for f in frames)
    assert 0.4 < np.mean([f.valid_fraction() for f in frames]) < 0.8
