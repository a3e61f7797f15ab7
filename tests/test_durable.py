"""Tests of ``pe_rlhf.durable``: whole writes, appends, atomic replacement, fsync and hashing."""

from __future__ import annotations

import errno
import hashlib
import os

import pytest

from pe_rlhf import durable


def test_write_bytes_writes_everything_even_when_the_os_writes_short(tmp_path, monkeypatch):
    real_write = os.write
    calls = []

    def short_write(fd, data):  # a pipe or a full-ish disk: at most 5 bytes a call
        calls.append(len(data))
        return real_write(fd, bytes(data[:5]))

    monkeypatch.setattr(os, "write", short_write)
    data = bytes(range(256)) * 3
    durable.write_bytes(tmp_path / "f.bin", data)
    monkeypatch.undo()
    assert (tmp_path / "f.bin").read_bytes() == data
    assert len(calls) == -(-len(data) // 5)


def test_write_bytes_truncates_or_appends(tmp_path):
    path = tmp_path / "log.jsonl"
    durable.write_bytes(path, b"a much longer first line\n")
    durable.write_bytes(path, b"one\n")
    durable.write_bytes(path, b"two\n", append=True)
    assert path.read_bytes() == b"one\ntwo\n"


def test_replace_bytes_swaps_whole_files_and_leaves_the_old_one_on_failure(tmp_path, monkeypatch):
    path = tmp_path / "latest"
    assert durable.replace_bytes(path, b"ckpt_1\n") == path
    durable.replace_bytes(path, b"ckpt_2\n")
    assert path.read_bytes() == b"ckpt_2\n"

    def full(target, data, append=False):
        with open(target, "wb") as f:
            f.write(data[:2])  # half the bytes land, then the disk is full
        raise OSError(errno.ENOSPC, "No space left on device", str(target))

    monkeypatch.setattr(durable, "write_bytes", full)
    with pytest.raises(OSError, match="No space left"):
        durable.replace_bytes(path, b"ckpt_3\n")
    assert path.read_bytes() == b"ckpt_2\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["latest"]  # no temp file left behind


def test_replace_bytes_uses_the_given_temp_name(tmp_path, monkeypatch):
    seen = []
    real_write = durable.write_bytes
    monkeypatch.setattr(durable, "write_bytes", lambda p, d, append=False: (seen.append(p.name), real_write(p, d)))
    durable.replace_bytes(tmp_path / "000001.pt", b"x", tmp=tmp_path / ".000001.pt.tmp")
    assert seen == [".000001.pt.tmp"] and (tmp_path / "000001.pt").read_bytes() == b"x"


def test_fsync_path_on_files_and_directories(tmp_path, monkeypatch):
    (tmp_path / "f").write_bytes(b"data")
    synced = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(fd), real_fsync(fd)))
    durable.fsync_path(tmp_path / "f")
    durable.fsync_path(tmp_path)
    assert len(synced) == 2


def test_fsync_path_skips_directories_on_windows(tmp_path, monkeypatch):
    """Windows cannot open a directory; NTFS journals the rename itself, so the sync is skipped."""
    real_open = os.open

    def windows_open(path, flags, *args):
        if os.path.isdir(path):
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_open(path, flags, *args)

    monkeypatch.setattr(durable, "_WINDOWS", True)
    monkeypatch.setattr(os, "open", windows_open)
    durable.fsync_path(tmp_path)  # no error
    durable.replace_bytes(tmp_path / "state.json", b"{}")  # the whole atomic write works there
    assert (tmp_path / "state.json").read_bytes() == b"{}"


def test_sha256_file_matches_hashlib_across_chunks(tmp_path, monkeypatch):
    monkeypatch.setattr(durable, "_HASH_CHUNK", 7)
    data = os.urandom(1000)
    (tmp_path / "blob").write_bytes(data)
    assert durable.sha256_file(tmp_path / "blob") == hashlib.sha256(data).hexdigest()
