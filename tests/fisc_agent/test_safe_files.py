"""The bounded file reader behind every file argument (fisc_agent.common.safe_files)."""

from __future__ import annotations

import os
import socket

import pytest

from fisc_agent.map.codec import MapError, load_map, read_public_key
from fisc_agent.common.safe_files import FileInputError, check_regular_file, read_head, read_regular_file


def test_a_regular_file_within_the_cap_is_read_whole(tmp_path):
    p = tmp_path / "f.bin"
    p.write_bytes(b"MAGIC" + bytes(range(256)) * 10)
    assert read_regular_file(p, what="test file", max_bytes=4096, magic=b"MAGIC") == p.read_bytes()
    assert read_regular_file(p, what="test file", max_bytes=len(p.read_bytes())) == p.read_bytes()  # cap inclusive
    assert check_regular_file(p, what="test file", max_bytes=4096, magic=(b"X", b"MAG")) == 2565
    assert read_head(p, 5, what="test file") == b"MAGIC"


@pytest.mark.parametrize("kind", ["chardev", "directory", "fifo", "socket"])
def test_non_regular_files_are_refused_without_reading(tmp_path, kind):
    if kind == "chardev":
        path, expect = "/dev/zero", "character device"
    elif kind == "directory":
        path, expect = tmp_path, "directory"
    elif kind == "fifo":
        path, expect = tmp_path / "fifo", "FIFO"
        os.mkfifo(path)  # nobody writes: a blocking open would hang here
    else:
        path, expect = tmp_path / "sock", "socket"
        s = socket.socket(socket.AF_UNIX)
        s.bind(str(path))
    with pytest.raises(FileInputError, match=f"must be a regular file, this is .*{expect}"):
        read_regular_file(path, what="test file", max_bytes=1 << 20)


def test_size_cap_magic_and_missing_file_name_the_check(tmp_path):
    p = tmp_path / "big.bin"
    p.write_bytes(b"M" * 2000)
    with pytest.raises(FileInputError, match=r"big\.bin: size: test file is 1\.95 KiB, larger than the 1000 bytes limit"):
        read_regular_file(p, what="test file", max_bytes=1000)
    with pytest.raises(FileInputError, match=r"big\.bin: magic: not a test file \(starts with b'MMMM"):
        read_regular_file(p, what="test file", max_bytes=4096, magic=b"FISC")
    with pytest.raises(FileInputError, match="not found"):
        read_regular_file(tmp_path / "nope", what="test file", max_bytes=10)


def test_a_sparse_file_is_refused_when_asked(tmp_path):
    p = tmp_path / "sparse.csv"
    with open(p, "wb") as fh:
        fh.write(b"x,y,z\n")
        fh.truncate(1 << 30)
    if os.lseek(os.open(p, os.O_RDONLY), 0, os.SEEK_HOLE) >= p.stat().st_size:
        pytest.skip("this file system does not report holes (SEEK_HOLE)")
    with pytest.raises(FileInputError, match="sparse: test file is a sparse file"):
        check_regular_file(p, what="test file", max_bytes=2 << 30, reject_sparse=True)
    assert check_regular_file(p, what="test file", max_bytes=2 << 30) == 1 << 30  # not asked: accepted


def test_map_and_key_readers_use_it_and_raise_map_errors(tmp_path):
    with pytest.raises(MapError, match="/dev/zero: file type: FISC map must be a regular file"):
        load_map("/dev/zero")
    with pytest.raises(MapError, match="/dev/zero: file type: Ed25519 public key file must be a regular file"):
        read_public_key("/dev/zero")
    big = tmp_path / "big.pub"
    big.write_text("00" * 5000)
    with pytest.raises(MapError, match="size: Ed25519 public key file"):
        read_public_key(big)
