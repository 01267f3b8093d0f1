"""hw.atomic: the old file or the whole new one, never a mix; no temp files left behind."""

from __future__ import annotations

import errno
import os
import stat

import pytest

from hw.atomic import AtomicFile, write_atomically


def test_write_replaces_the_whole_file(tmp_path):
    path = tmp_path / "state.bin"
    write_atomically(path, b"old")
    write_atomically(path, b"new contents")
    assert path.read_bytes() == b"new contents"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.bin"]


def test_permissions_follow_the_umask_like_open(tmp_path):
    path = tmp_path / "picture.png"
    old = os.umask(0o022)
    try:
        write_atomically(path, b"x")
    finally:
        os.umask(old)
    assert stat.S_IMODE(path.stat().st_mode) == 0o644


def test_an_error_inside_the_block_keeps_the_old_file(tmp_path):
    path = tmp_path / "state.bin"
    write_atomically(path, b"old")
    with pytest.raises(RuntimeError):
        with AtomicFile(path) as handle:
            handle.write(b"half")
            raise RuntimeError("crash while writing")
    assert path.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.bin"]


def test_a_writer_can_seek_back_and_patch_before_committing(tmp_path):
    target = AtomicFile(tmp_path / "rec.bin")
    target.file.write(b"HDR0payload")
    target.file.seek(3)
    target.file.write(b"1")
    assert not (tmp_path / "rec.bin").exists()
    target.commit()
    target.commit()  # a second commit does nothing
    assert (tmp_path / "rec.bin").read_bytes() == b"HDR1payload"


def test_discard_leaves_nothing(tmp_path):
    target = AtomicFile(tmp_path / "rec.bin")
    target.file.write(b"abc")
    target.discard()
    assert list(tmp_path.iterdir()) == []


def test_a_missing_folder_is_an_os_error(tmp_path):
    with pytest.raises(OSError):
        write_atomically(tmp_path / "nowhere" / "x.bin", b"x")


def test_a_folder_in_the_way_is_refused_before_writing(tmp_path):
    with pytest.raises(IsADirectoryError, match="is a folder") as info:
        write_atomically(tmp_path, b"x")
    assert info.value.filename == str(tmp_path) and list(tmp_path.iterdir()) == []


def fill(folder):
    """Fill the file system of ``folder`` with a file named filler."""
    with open(folder / "filler", "wb", buffering=0) as filler:
        with pytest.raises(OSError):
            while True:
                filler.write(b"x" * 4096)


@pytest.fixture
def full_disk(small_tmpfs):
    """A 64 KiB tmpfs, filled up (needs root: skipped elsewhere)."""
    folder = small_tmpfs("64k")
    fill(folder)
    return folder


def test_a_full_disk_leaves_no_temp_file(full_disk):
    """Issue 44: discard() closed the file first; on a full disk that close raised ENOSPC and
    the temp file stayed."""
    target = AtomicFile(full_disk / "last-check.json")
    target.file.write(b"{}" * 100)  # buffered: the disk says no only when it is flushed
    target.discard()
    with pytest.raises(OSError) as caught:
        write_atomically(full_disk / "view.mcap", b"x" * 10_000)
    assert caught.value.errno == errno.ENOSPC
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler"]
