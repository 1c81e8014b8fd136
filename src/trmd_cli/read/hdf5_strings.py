"""String attributes of HDF5 files, read without trusting a damaged global heap.

A variable-length string attribute (what h5py writes for ``attrs["format"] = "trmd"``) keeps
its characters in a global heap collection ("GCOL"). The HDF5 library walks every object of
that collection when it loads it, advancing by each object's stored size; a damaged size
that lands the walk on a free-space entry of size 0 makes the library loop forever, holding
the interpreter, so no timeout can stop it. Before such an attribute is read, its heap
collection is found through the object header it is stored in and walked here the same way;
a walk that would not advance, or would run past the collection, is reported as damage.

Only what is needed is parsed: version 1 object headers (h5py's default) and version 2 ones,
with attributes stored in the header or, beyond eight of them, densely in a fractal heap whose
root block is a direct block or an indirect block of direct blocks (the attribute message is
found by its name there, not through the name index). Anything else is read as before.
"""

from __future__ import annotations

import os
import struct

#: HDF5 message types: attribute, header continuation, attribute info (dense storage)
_ATTRIBUTE, _CONTINUATION, _ATTRIBUTE_INFO = 0x000C, 0x0010, 0x0015
#: an address that points nowhere
_UNDEFINED = 0xFFFFFFFFFFFFFFFF


class DamagedHeap(OSError):
    """A global heap collection whose walk would not end (see the module docstring); an
    ``OSError``, as h5py reports other damage."""


def read_attr(obj, name: str):
    """``obj.attrs.get(name)`` (an h5py File or Group), raising :class:`DamagedHeap` instead
    of hanging when the attribute is a variable-length string in a damaged heap (any other
    attribute is read as h5py reads it)."""
    import h5py

    if name not in obj.attrs:
        return None
    aid = h5py.h5a.open(obj.id, name.encode())
    kind = aid.get_type()
    if isinstance(kind, h5py.h5t.TypeStringID) and kind.is_variable_str():
        heap = _heap_address(obj, name)
        if heap is not None:
            check_heap(obj.file.filename, heap)
    return obj.attrs.get(name)


def _read(fh, size: int) -> bytes:
    """``size`` bytes from ``fh``'s position, or up to the file's end: a size read from a
    damaged file (up to 2⁶⁴) is never allocated whole."""
    left = os.fstat(fh.fileno()).st_size - fh.tell()
    return fh.read(max(min(size, left), 0))


def check_heap(path, address: int) -> None:
    """Walk the global heap collection at byte ``address`` of the file ``path`` as the HDF5
    library does (H5HG's deserialisation); raise :class:`DamagedHeap` where it would not
    end. A block that is not a collection is left to the library (which reports it)."""
    with open(path, "rb") as fh:
        fh.seek(address)
        head = _read(fh, 16)
        if len(head) < 16 or head[:4] != b"GCOL":
            return
        size = struct.unpack_from("<Q", head, 8)[0]
        if size < 16 or size > (1 << 31):
            raise DamagedHeap(f"global heap at byte {address} claims {size} bytes")
        chunk = head + _read(fh, size - 16)
    if len(chunk) < size:
        # the library reads the collection whole, and fails on a short one
        return
    p = 16
    while p < size:
        if p + 16 > size:
            break  # too small for an object header: free space, the walk ends
        idx, _, _, osize = struct.unpack_from("<HHIQ", chunk, p)
        need = 16 + ((osize + 7) & ~7) if idx > 0 else osize
        if need <= 0 or p + need > size:
            raise DamagedHeap(f"global heap at byte {address}: object {idx} at offset {p} "
                              f"has size {osize}")
        p += need


def _heap_address(obj, name: str) -> int | None:
    """The global heap collection address of the variable-length string attribute ``name``
    of ``obj``, read from its object header; None where the header is not understood."""
    import h5py

    key = name.encode()
    try:
        info = h5py.h5o.get_info(obj.id)
        with open(obj.file.filename, "rb") as fh:
            for body in _attribute_messages(fh, int(info.addr), key):
                found = _string_heap(body, key)
                if found is not None:
                    return found
    except (OSError, struct.error, ValueError):
        return None
    return None


def _attribute_messages(fh, addr: int, name: bytes):
    """The attribute messages' bodies in the object header at ``addr`` (v1 or v2), and in
    its dense storage the candidates for attribute ``name``."""
    fh.seek(addr)
    first = _read(fh, 16)
    if first[:4] == b"OHDR":
        yield from _v2_messages(fh, addr, name)
        return
    if not first or first[0] != 1:
        return
    nmsgs, _, size = struct.unpack_from("<HII", first, 2)
    blocks = [(addr + 16, size)]
    seen = 0
    while blocks and seen < nmsgs:
        start, length = blocks.pop(0)
        fh.seek(start)
        data = _read(fh, length)
        p = 0
        while p + 8 <= len(data) and seen < nmsgs:
            mtype, msize = struct.unpack_from("<HH", data, p)
            body = data[p + 8:p + 8 + msize]
            seen += 1
            if mtype == _ATTRIBUTE:
                yield body
            elif mtype == _CONTINUATION and len(body) >= 16:
                blocks.append(struct.unpack_from("<QQ", body, 0))
            p += 8 + msize


def _v2_messages(fh, addr: int, name: bytes):
    fh.seek(addr)
    head = _read(fh, 64)
    flags = head[5]
    p = 6 + (16 if flags & 0x20 else 0) + (4 if flags & 0x10 else 0)
    width = 1 << (flags & 0x03)
    size = int.from_bytes(head[p:p + width], "little")
    start = addr + p + width
    order = 2 if flags & 0x04 else 0
    blocks = [(start, size)]
    while blocks:
        start, length = blocks.pop(0)
        fh.seek(start)
        data = _read(fh, length)
        q = 4 if data[:4] == b"OCHK" else 0
        end = len(data) - (4 if q else 0)
        while q + 4 + order <= end:
            mtype = data[q]
            msize = struct.unpack_from("<H", data, q + 1)[0]
            body = data[q + 4 + order:q + 4 + order + msize]
            if mtype == _ATTRIBUTE:
                yield body
            elif mtype == _ATTRIBUTE_INFO:
                yield from _dense_candidates(fh, body, name)
            elif mtype == _CONTINUATION and len(body) >= 16:
                blocks.append(struct.unpack_from("<QQ", body, 0))
            q += 4 + order + msize


def _dense_candidates(fh, info: bytes, name: bytes):
    """From an attribute info message's body: what follows each place in the fractal heap's
    direct blocks where an attribute message (version 2 or 3) named ``name`` could start."""
    if len(info) < 10 or info[0] != 0:
        return
    p = 2 + (2 if info[1] & 0x01 else 0)
    heap = struct.unpack_from("<Q", info, p)[0]
    if heap == _UNDEFINED:
        return  # attributes in the header (a version 2 header has this message either way)
    key = name + b"\x00"
    for block in _direct_blocks(fh, heap):
        at = block.find(key)
        while at >= 0:
            for start, version in ((at - 9, 3), (at - 8, 2)):
                if start >= 0 and block[start] == version and \
                        struct.unpack_from("<H", block, start + 2)[0] == len(key):
                    yield block[start:]
            at = block.find(key, at + 1)


def _direct_blocks(fh, heap: int):
    """The direct blocks' bytes of the fractal heap whose header is at ``heap``: its root
    block, or the direct blocks an indirect root lists (deeper heaps, filtered ones and huge
    objects are not followed)."""
    fh.seek(heap)
    head = _read(fh, 142)
    if len(head) < 142 or head[:4] != b"FRHP" or struct.unpack_from("<H", head, 7)[0]:
        return  # not a heap, or one with I/O filters
    width = struct.unpack_from("<H", head, 110)[0]
    start_size, max_direct = struct.unpack_from("<QQ", head, 112)
    max_bits = struct.unpack_from("<H", head, 128)[0]
    root, rows = struct.unpack_from("<QH", head, 132)
    if rows == 0:
        fh.seek(root)
        yield _read(fh, start_size)
        return
    if not 0 < start_size <= max_direct or width == 0 or width > 1024:
        return
    # the doubling table: rows 0 and 1 hold blocks of the starting size, each later row
    # twice the last; rows of blocks larger than ``max_direct`` point to indirect blocks
    sizes = [start_size if r < 2 else start_size << (r - 1) for r in range(rows)]
    fh.seek(root)
    ind = _read(fh, 4 + 1 + 8 + (max_bits + 7) // 8 + 8 * width * rows)
    if ind[:4] != b"FHIB":
        return
    q = 13 + (max_bits + 7) // 8
    for size in sizes:
        if size > max_direct:
            return
        for _ in range(width):
            addr = struct.unpack_from("<Q", ind, q)[0]
            q += 8
            if addr != _UNDEFINED:
                fh.seek(addr)
                yield _read(fh, size)


def _string_heap(body: bytes, name: bytes) -> int | None:
    """The heap address in an attribute message's data when it is attribute ``name``."""
    if len(body) < 8:
        return None
    version = body[0]
    nsize, tsize, ssize = struct.unpack_from("<HHH", body, 2)
    p = 8 + (1 if version >= 3 else 0)

    def step(n: int) -> int:
        return (n + 7) & ~7 if version == 1 else n

    got = body[p:p + nsize].rstrip(b"\x00")
    p += step(nsize)
    dtype = body[p:p + tsize]
    p += step(tsize) + step(ssize)
    if got != name or not dtype or (dtype[0] & 0x0F) != 9:
        return None
    if len(body) < p + 16:
        return None
    # a scalar variable-length value: its length (4), then the heap ID: address (8), index (4)
    return struct.unpack_from("<Q", body, p + 4)[0]
