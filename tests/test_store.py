"""robot_change.service.store: verified per-station references; a bad file is quarantined and
reported, never used; a kill -9 in the middle of a save leaves the previous reference whole."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import threading

import numpy as np
import pytest
import store_faults
from conftest import SIM_FIXTURES

from hw.depth import open_depth
from robot_change.change.scene import SceneModel, build_scene
from robot_change.errors import (
    ConfigError,
    MessageError,
    ReferenceMissing,
    StationNameError,
    StoreError,
)
from robot_change.link.protocol import Captured
from robot_change.service.store import ReferenceStore, check_station


@pytest.fixture(scope="module")
def scenes() -> tuple[SceneModel, SceneModel]:
    """Two references of the bundled VGA room (~0.6 MB each), told apart by ``source``."""
    with open_depth(str(SIM_FIXTURES / "frames" / "room_vga.png")) as source:
        frame = next(iter(source))
    a = build_scene([frame], source="A")
    return a, dataclasses.replace(a, source="B")


def same(x: SceneModel, y: SceneModel) -> bool:
    return (x.source == y.source and np.array_equal(x.depth, y.depth)
            and np.array_equal(x.points, y.points)
            and np.array_equal(x.mixture.means, y.mixture.means))


# ---------------------------------------------------------------------------------------------
# saving and loading


def test_save_load_and_the_previous_version(tmp_path, scenes):
    a, b = scenes
    store = ReferenceStore(tmp_path / "refs")
    assert store.stations() == []
    path = store.save("dock", a)
    assert path == tmp_path / "refs" / "dock.scene.npz"
    assert same(store.load("dock"), a)
    assert not store.previous_path("dock").exists()
    store.save("dock", b)
    assert same(store.load("dock"), b)
    assert same(store.load_previous("dock"), a)
    assert sorted(p.name for p in (tmp_path / "refs").iterdir()) == [
        "dock.prev.scene.npz", "dock.scene.npz"]  # no temp file left behind


def test_stations_info_and_delete(tmp_path, scenes):
    a, b = scenes
    store = ReferenceStore(tmp_path)
    store.save("dock", a)
    store.save("dock", b)
    store.save("kitchen-2", a)
    (tmp_path / "notes.txt").write_text("not a reference")
    (tmp_path / "bad name.scene.npz").write_bytes(b"")
    assert store.stations() == ["dock", "kitchen-2"]
    info = store.info("dock")
    assert info.current.path == store.path("dock") and info.current.size > 100_000
    assert info.previous.path == store.previous_path("dock")
    assert info.quarantined == ()
    assert store.info("kitchen-2").previous is None
    assert store.delete("dock") == [store.path("dock"), store.previous_path("dock")]
    assert store.stations() == ["kitchen-2"]
    assert store.delete("dock") == []
    with pytest.raises(ReferenceMissing, match="no reference stored") as info_missing:
        store.load("dock")
    assert info_missing.value.station == "dock" and info_missing.value.quarantined is None


def test_a_missing_reference_is_a_typed_error_naming_the_station(tmp_path):
    store = ReferenceStore(tmp_path / "never-created")
    with pytest.raises(ReferenceMissing, match=r"station 'dock': no reference stored .*"
                       "CAPTURE_REFERENCE dock"):
        store.load("dock")
    assert store.stations() == [] and store.info("dock").current is None
    assert isinstance(ReferenceMissing("x"), LookupError)


@pytest.mark.parametrize("name", ["", "../etc", "a/b", "/abs", "dock.prev", ".hidden", "..",
                                  "a" * 33, "dock\n", "dock ", "café", "-dash", None, 5])
def test_station_names_are_names_never_paths(tmp_path, scenes, name):
    store = ReferenceStore(tmp_path)
    for call in (lambda: store.save(name, scenes[0]), lambda: store.load(name),
                 lambda: store.delete(name), lambda: store.info(name),
                 lambda: store.load_previous(name)):
        with pytest.raises(StationNameError, match="a station name is 1..32 ASCII letters"):
            call()
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(MessageError):  # the protocol refuses the same names on the wire
        Captured(station=name)


@pytest.mark.parametrize("name", ["a", "A0", "dock_1", "kitchen-2", "x" * 32])
def test_valid_station_names_agree_with_the_protocol(name):
    assert check_station(name) == name
    assert Captured(station=name).station == name


def test_an_unwritable_folder_is_a_store_error(tmp_path, scenes):
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(StoreError, match="cannot write its reference in .*check free space"):
        ReferenceStore(blocker / "refs").save("dock", scenes[0])


# ---------------------------------------------------------------------------------------------
# damaged, foreign and newer files: quarantined and reported, never used, never deleted


def _rewrite_header(data: bytes, **changes) -> bytes:
    """The same .npz with header fields changed (the checksum is not recomputed)."""
    with np.load(io.BytesIO(data)) as npz:
        arrays = {k: npz[k] for k in npz.files}
    header = json.loads(str(arrays["header"][()]))
    header.update(changes)
    arrays["header"] = np.array(json.dumps(header))
    out = io.BytesIO()
    np.savez(out, **arrays)
    return out.getvalue()


def _tamper_depth(data: bytes) -> bytes:
    with np.load(io.BytesIO(data)) as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays["depth"] = arrays["depth"].copy()
    arrays["depth"][100, 100] += 1
    out = io.BytesIO()
    np.savez(out, **arrays)
    return out.getvalue()


DAMAGE = {
    "truncated": lambda data: data[: len(data) // 2],
    "empty": lambda data: b"",
    "tampered": _tamper_depth,
    "foreign": lambda data: _rewrite_header(data, format="someone.else"),
    "newer": lambda data: _rewrite_header(data, version=99),
    "not npz": lambda data: b"\x89PNG\r\n\x1a\n" + bytes(1000),
}


@pytest.mark.parametrize("damage", sorted(DAMAGE))
def test_a_bad_reference_is_quarantined_reported_and_never_used(tmp_path, scenes, damage):
    a, b = scenes
    store = ReferenceStore(tmp_path)
    store.save("dock", a)
    store.save("dock", b)
    bad = DAMAGE[damage](store.path("dock").read_bytes())
    store.path("dock").write_bytes(bad)
    with pytest.raises(ReferenceMissing) as info:
        store.load("dock")
    err = info.value
    assert err.station == "dock"
    moved = err.quarantined
    assert moved.parent == tmp_path / "quarantine" and moved.name.startswith("dock.scene.npz.")
    assert moved.read_bytes() == bad  # kept as it was, for a post-mortem
    assert moved.with_name(moved.name + ".txt").read_text().startswith(str(store.path("dock")))
    message = str(err)
    assert "failed verification" in message and str(moved) in message
    assert "CAPTURE_REFERENCE dock" in message and "dock.prev.scene.npz (load_previous)" in message
    # not used, not silently replaced by the previous one
    assert not store.path("dock").exists()
    with pytest.raises(ReferenceMissing, match="no reference stored.*or use the previous"):
        store.load("dock")
    assert same(store.load_previous("dock"), a)  # only on request
    assert store.info("dock").quarantined == (moved,)
    assert store.stations() == []


@contextlib.contextmanager
def _as_nobody():
    """This process's file access as the user nobody (root reads every file), then back."""
    if os.geteuid() != 0:
        yield
        return
    os.setegid(65534)
    os.seteuid(65534)
    try:
        yield
    finally:
        os.seteuid(0)
        os.setegid(0)


def test_a_reference_the_service_may_not_read_is_a_storage_error_and_stays(tmp_path, scenes):
    """A sound file the service's user may not read (a root-owned 0600 copy) is a storage
    error naming the permissions: not quarantined as damaged, as it was."""
    a, _ = scenes
    store = ReferenceStore(tmp_path)
    store.save("dock", a)
    store.path("dock").chmod(0)
    with _as_nobody(), pytest.raises(StoreError, match="cannot read .*permissions"):
        store.load("dock")
    assert store.path("dock").exists() and not store.quarantine_dir.exists()
    store.path("dock").chmod(0o600)
    assert same(store.load("dock"), a)


def test_a_quarantine_that_cannot_be_written_is_a_storage_error_and_loses_nothing(
        tmp_path, scenes):
    """A damaged reference whose quarantine folder cannot be made (a file in its place, as a
    folder the service may not write): a storage error naming it, for a check and for the
    capture that would replace it (they raised an internal error and 'cannot write its
    reference'), the damaged file left where it was; once fixed, the capture goes through."""
    a, b = scenes
    store = ReferenceStore(tmp_path)
    store.save("dock", a)
    bad = store.path("dock").read_bytes()[:1000]
    store.path("dock").write_bytes(bad)
    store.quarantine_dir.write_text("not a folder")
    for attempt in (lambda: store.load("dock"), lambda: store.save("dock", b)):
        with pytest.raises(StoreError, match="failed verification and cannot be moved to "
                                             f"{store.quarantine_dir}"):
            attempt()
        assert store.path("dock").read_bytes() == bad
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dock.scene.npz", "quarantine"]
    store.quarantine_dir.unlink()
    store.save("dock", b)
    assert same(store.load("dock"), b)
    [moved] = store.info("dock").quarantined
    assert moved.read_bytes() == bad


def test_a_fifo_in_place_of_a_reference_is_quarantined_not_waited_on(tmp_path, scenes):
    store = ReferenceStore(tmp_path)
    store.save("dock", scenes[0])
    store.path("dock").unlink()
    os.mkfifo(store.path("dock"))
    raised = []
    loader = threading.Thread(target=lambda: raised.append(_raised(store.load, "dock")),
                              daemon=True)
    loader.start()
    loader.join(20)
    assert not loader.is_alive(), "loading a FIFO blocked (waiting for a writer)"
    [err] = raised
    assert isinstance(err, ReferenceMissing) and "not a regular file" in str(err)
    assert err.quarantined is not None and not store.path("dock").exists()


def _raised(fn, *args) -> BaseException | None:
    try:
        fn(*args)
    except BaseException as exc:  # noqa: BLE001 - handed to the test's thread
        return exc
    return None


def test_a_bad_previous_is_quarantined_too(tmp_path, scenes):
    store = ReferenceStore(tmp_path)
    store.save("dock", scenes[0])
    store.save("dock", scenes[1])
    store.previous_path("dock").write_bytes(b"garbage")
    with pytest.raises(ReferenceMissing, match="previous reference dock.prev.scene.npz failed"):
        store.load_previous("dock")
    assert same(store.load("dock"), scenes[1])


def test_saving_over_a_bad_reference_keeps_the_good_previous(tmp_path, scenes):
    a, b = scenes
    store = ReferenceStore(tmp_path)
    store.save("dock", a)
    store.save("dock", a)  # previous = a
    store.path("dock").write_bytes(b"garbage")
    store.save("dock", b)
    assert same(store.load("dock"), b)
    assert same(store.load_previous("dock"), a)  # not the garbage
    [moved] = store.info("dock").quarantined
    assert moved.read_bytes() == b"garbage"


# ---------------------------------------------------------------------------------------------
# kill -9 while writing, a full disk (tests/store_faults.py; 100 kills: bench/bench_store_faults.py)


def test_kill_9_in_a_save_never_loses_the_previous_reference(tmp_path, scenes):
    """32 kills, aimed 8 at each moment of store_faults.MOMENTS: the store always holds A and
    B, one current and one previous (before issue 44 a kill while the current was copied over
    the previous left the previous a copy of the current).  The link's window is a few
    microseconds, seldom hit: the state a kill there leaves is made by hand in the next test."""
    result = store_faults.kill_saves(tmp_path, *scenes, kills=32)
    assert result["previous_lost"] == 0, result
    assert all(result["hits"][m] >= 4 for m in store_faults.MOMENTS[:3]), result


def test_a_save_on_a_full_disk_changes_nothing(small_tmpfs, scenes):
    """A real tmpfs with room for two references and half a third: every save fails with a
    StoreError; current and previous stay, no temp file (before issue 44, 6 of 6 lost the
    previous)."""
    result = store_faults.full_disk_saves(small_tmpfs("2m"), *scenes, trials=6)
    assert result == {"trials": 6, "failed": 6, "previous_lost": 0}


def test_recover_completes_a_save_killed_between_its_renames(tmp_path, scenes):
    a, b = scenes
    store = ReferenceStore(tmp_path)
    store.save("dock", a)
    b.save(store.next_path("dock"))
    os.link(store.path("dock"), store.previous_path("dock"))  # the save was killed here
    assert store.recover() == [store.next_path("dock")]
    assert same(store.load("dock"), b) and same(store.load_previous("dock"), a)
    b.save(store.next_path("dock"))  # killed before it kept the previous: nothing changes
    (tmp_path / ".dock.scene.npz.x1y2.tmp").write_bytes(b"half")
    store.recover()
    assert same(store.load("dock"), b) and same(store.load_previous("dock"), a)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dock.prev.scene.npz",
                                                           "dock.scene.npz"]


def test_a_new_station_beyond_the_limit_is_refused_and_an_old_one_still_saves(tmp_path, scenes):
    store = ReferenceStore(tmp_path, max_stations=2)
    store.save("a", scenes[0])
    store.save("b", scenes[0])
    with pytest.raises(StoreError, match=r"'c' refused: the store holds 2 stations") as info:
        store.save("c", scenes[0])
    assert str(tmp_path) not in str(info.value)  # the text goes over the wire: no paths
    assert store.stations() == ["a", "b"]
    store.save("a", scenes[1])  # capturing a station again is always allowed
    assert store.stations() == ["a", "b"]


def test_a_save_that_would_fill_the_disk_is_refused(tmp_path, scenes):
    import shutil

    free_mb = shutil.disk_usage(tmp_path).free / 1e6
    store = ReferenceStore(tmp_path, min_free_mb=int(free_mb) + 10)
    with pytest.raises(StoreError, match="MB free on the module's disk") as info:
        store.save("dock", scenes[0])
    assert str(tmp_path) not in str(info.value)
    assert store.stations() == []
    ReferenceStore(tmp_path, min_free_mb=0).save("dock", scenes[0])


def test_the_store_limits_come_from_the_configuration():
    from robot_change.service.config import config_from_dict

    config = config_from_dict({"store": {"max_stations": 5, "min_free_mb": 7}}, "x.toml")
    assert (config.store.max_stations, config.store.min_free_mb) == (5, 7)
    with pytest.raises(ConfigError, match="store.max_stations = 0"):
        config_from_dict({"store": {"max_stations": 0}}, "x.toml")
