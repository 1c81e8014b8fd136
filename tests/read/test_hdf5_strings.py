"""String attributes of HDF5 files: a damaged global heap is reported, not looped on."""

from __future__ import annotations

import struct
import subprocess
import sys

import h5py
import numpy as np
import pytest

from trmd_cli.events import Exposure, make_stream
from trmd_cli.read.hdf5_strings import (
    DamagedHeap,
    _direct_blocks,
    _heap_address,
    check_heap,
    read_attr,
)
from trmd_cli.write import write_h5


def _trmd_file(path):
    rng = np.random.default_rng(3)
    s = make_stream(rng.integers(0, 64, 40), rng.integers(0, 48, 40),
                    np.sort(rng.integers(0, 10_000, 40)), rng.integers(0, 2, 40), 64, 48)
    write_h5(path, s, blurry=np.full((2, 48, 64), 0.5, np.float32),
             exposures=[Exposure(0, 4000), Exposure(5000, 9000)])
    return path


def _zero_first_heap_object(path) -> int:
    """Set the size of the first object of the file's global heap to 0: the walk then steps
    into the string's bytes and onto a free-space entry of size 0 (the HDF5 library loops
    there forever). Returns the collection's address."""
    raw = bytearray(path.read_bytes())
    at = raw.find(b"GCOL")
    assert at > 0 and struct.unpack_from("<H", raw, at + 16)[0] == 1
    raw[at + 24:at + 32] = bytes(8)
    path.write_bytes(bytes(raw))
    return at


@pytest.mark.parametrize("libver", ["earliest", "latest"])
def test_heap_found_through_the_object_header(tmp_path, libver):
    """Version 1 and version 2 object headers lead to the collection that holds the
    string, found independently by its signature; the values read are h5py's."""
    path = tmp_path / "a.h5"
    with h5py.File(path, "w", libver=libver) as f:
        f.attrs["width"] = 64
        f.attrs["format"] = "trmd"
        f.attrs["other"] = "x" * 40
    gcol = path.read_bytes().find(b"GCOL")
    with h5py.File(path, "r") as f:
        assert _heap_address(f, "format") == gcol == _heap_address(f, "other")
        assert read_attr(f, "format") == "trmd" and read_attr(f, "other") == "x" * 40
        assert read_attr(f, "width") == 64 and read_attr(f, "missing") is None


def test_heap_walk_on_hand_made_collections(tmp_path):
    """A collection of one 4-byte object then free space walks to its end; the same with
    the free-space entry's size 0 (the walk would not advance) or an object running past
    the collection is damage."""
    def collection(objects):
        body = b"".join(struct.pack("<HHIQ", i, 1, 0, n) + data.ljust((n + 7) & ~7, b"\0")
                        for i, n, data in objects)
        size = 16 + len(body) + 32
        free = struct.pack("<HHIQ", 0, 0, 0, 32)
        return b"GCOL" + bytes([1, 0, 0, 0]) + struct.pack("<Q", size) + body + free + \
            bytes(16)

    good = tmp_path / "g.bin"
    good.write_bytes(collection([(1, 4, b"trmd")]))
    check_heap(good, 0)
    looping = tmp_path / "l.bin"
    raw = bytearray(collection([(1, 4, b"trmd")]))
    raw[16 + 24 + 8:16 + 24 + 16] = bytes(8)  # the free-space entry's size: 0
    looping.write_bytes(bytes(raw))
    with pytest.raises(DamagedHeap):
        check_heap(looping, 0)
    past = tmp_path / "p.bin"
    raw = bytearray(collection([(1, 4, b"trmd")]))
    raw[16 + 8:16 + 16] = struct.pack("<Q", 10_000)  # the string's size: past the end
    past.write_bytes(bytes(raw))
    with pytest.raises(DamagedHeap):
        check_heap(past, 0)


def test_damaged_heap_is_an_error_not_a_hang(tmp_path):
    """The damage that made the HDF5 library loop forever on ``attrs["format"]``: every
    reader of trmd HDF5 files reports it with the file's path. Run in a child process with
    a time limit, so that a regression fails instead of hanging the suite."""
    path = _trmd_file(tmp_path / "frames.h5")
    _zero_first_heap_object(path)
    code = f"""
import sys
from pathlib import Path
from trmd_cli.errors import TrmdError
from trmd_cli.read import open_events
from trmd_cli.simulate.dataset import H5SampleDataset
from trmd_cli.train.data import detect_kind
p = Path({str(path)!r})
said = []
for read in (lambda: open_events(p), lambda: H5SampleDataset(p), lambda: detect_kind(p)):
    try:
        read()
    except TrmdError as e:
        assert e.path is not None
        said.append(str(e))
print(len(said)); print(said[0])
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    count, first = out.stdout.splitlines()[:2]
    assert count == "3" and "global heap" in first


def _dense_file(path, count: int, long: bool):
    """A file whose root holds ``count`` attributes besides two strings, in dense storage
    (version 2 object header, more than eight attributes): with ``long`` ones the fractal
    heap outgrows one direct block and its root becomes an indirect block."""
    with h5py.File(path, "w", libver="latest") as f:
        for i in range(count):
            f.attrs[f"a{i:02d}"] = f"value {i} " * 25 if long else i
        f.attrs["format"] = "trmd"
        f.attrs["other"] = "x" * 40
    return path


@pytest.mark.parametrize("count, long, root", [(12, False, b"FHDB"), (60, True, b"FHIB")])
def test_heap_found_through_dense_attribute_storage(tmp_path, count, long, root):
    """Attributes kept in a fractal heap (direct or indirect root block) lead to the global
    heap collection that holds each string's characters, checked on the file's bytes."""
    path = _dense_file(tmp_path / "d.h5", count, long)
    raw = path.read_bytes()
    heap = raw.find(b"FRHP")
    assert heap > 0 and raw[struct.unpack_from("<Q", raw, heap + 132)[0]:][:4] == root
    names = ["format", "other"] + ([f"a{i:02d}" for i in range(count)] if long else [])
    with h5py.File(path, "r") as f:
        for name in names:
            value = read_attr(f, name)
            at = _heap_address(f, name)
            assert at is not None and raw[at:at + 4] == b"GCOL", name
            size = struct.unpack_from("<Q", raw, at + 8)[0]
            assert value.encode() in raw[at:at + size], name


def test_damaged_heap_in_dense_storage_is_an_error_not_a_hang(tmp_path):
    """The looping damage behind a densely stored string attribute is reported too (in a
    child process with a time limit: a regression would hang in the HDF5 library)."""
    path = _dense_file(tmp_path / "d.h5", 12, False)
    _zero_first_heap_object(path)
    code = f"""
import h5py
from trmd_cli.read.hdf5_strings import DamagedHeap, read_attr
with h5py.File({str(path)!r}, "r") as f:
    assert read_attr(f, "a03") == 3
    try:
        read_attr(f, "format")
    except DamagedHeap as e:
        print(e)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert "global heap" in out.stdout


def test_sizes_past_the_file_are_read_as_far_as_it_goes(tmp_path):
    """A damaged size in the fractal heap's header (the root block 2⁵⁰ bytes long) is read
    up to the file's end, not allocated (h5py, which checks the header's checksum first, is
    left out: the walk here must not depend on it)."""
    path = _dense_file(tmp_path / "d.h5", 12, False)
    raw = bytearray(path.read_bytes())
    heap = raw.find(b"FRHP")
    root = struct.unpack_from("<Q", raw, heap + 132)[0]
    raw[heap + 112:heap + 120] = struct.pack("<Q", 1 << 50)  # the starting block size
    path.write_bytes(bytes(raw))
    with open(path, "rb") as fh:
        blocks = list(_direct_blocks(fh, heap))
    assert len(blocks) == 1 and blocks[0] == bytes(raw[root:])
