"""robot_change.npzfile: the one checksummed, versioned .npz format (scenes, mixtures, checks),
read back by numpy's own reader and by ours."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from robot_change import npzfile
from robot_change.errors import RobotChangeError

ARRAYS = {"depth": np.arange(12, dtype=np.uint16).reshape(3, 4),
          "mask": np.eye(3, dtype=bool), "boxes": np.zeros((0, 10))}


class Oops(RobotChangeError):
    pass


def _read(path, version=1, names=("depth", "mask", "boxes")):
    return npzfile.read(path, "test.format", version, names, Oops, "write it again")


@pytest.mark.parametrize("compress", [True, False])
def test_round_trip_and_numpy_reads_it(tmp_path, compress):
    path = tmp_path / "a.npz"
    written = npzfile.write(path, "test.format", 1, ARRAYS, {"station": "dock"},
                            compress=compress)
    header, arrays = _read(path)
    assert header == written and header["station"] == "dock"
    assert header["arrays"]["depth"] == ["<u2", [3, 4]]
    for name, a in ARRAYS.items():
        np.testing.assert_array_equal(arrays[name], a)
        assert arrays[name].dtype == a.dtype
    with np.load(path, allow_pickle=False) as data:  # the real library's reader
        assert json.loads(str(data["header"][()]))["format"] == "test.format"
        np.testing.assert_array_equal(data["depth"], ARRAYS["depth"])
    assert [p.name for p in tmp_path.iterdir()] == ["a.npz"]  # no temp file left


def _resave(path, header=None, **arrays):
    with np.load(path) as data:
        items = {k: data[k] for k in data.files}
    h = json.loads(str(items["header"][()]))
    h.update(header or {})
    items["header"] = np.array(json.dumps(h))
    items.update(arrays)
    np.savez(path, **items)


@pytest.mark.parametrize("header, arrays, match", [
    (None, {"depth": np.zeros((3, 4), np.uint16)}, "checksum mismatch"),
    ({"station": "other"}, {}, "checksum mismatch"),
    ({"format": "other"}, {}, "'other' is not 'test.format'"),
    ({"version": 2}, {}, "reads up to version 1: upgrade"),
    ({"version": "1"}, {}, "bad format version"),
])
def test_changed_files_are_refused(tmp_path, header, arrays, match):
    path = tmp_path / "a.npz"
    npzfile.write(path, "test.format", 1, ARRAYS)
    _resave(path, header, **arrays)
    with pytest.raises(Oops, match=match):
        _read(path)


def test_broken_and_foreign_files_are_typed_errors(tmp_path):
    path = tmp_path / "a.npz"
    npzfile.write(path, "test.format", 1, ARRAYS)
    raw = path.read_bytes()
    (tmp_path / "half.npz").write_bytes(raw[: len(raw) // 2])
    (tmp_path / "text.npz").write_bytes(b"not a zip")
    np.save(tmp_path / "one.npy", np.zeros(3))
    with zipfile.ZipFile(tmp_path / "nohdr.npz", "w") as z:
        z.writestr("depth.npy", b"")
    for name, match in (("half.npz", "truncated or damaged.*write it again"),
                        ("text.npz", "not an .npz archive"), ("one.npy", "single .npy"),
                        ("nohdr.npz", "no header")):
        with pytest.raises(Oops, match=match):
            _read(tmp_path / name)
    with pytest.raises(Oops, match=r"\['extra'\] are missing"):
        _read(path, names=("depth", "extra"))
    with pytest.raises(FileNotFoundError):
        _read(tmp_path / "absent.npz")
