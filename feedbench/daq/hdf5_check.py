"""A structural pre-check of an HDF5 file from outside, before libhdf5 reads it.

libhdf5 (2.0.0, as h5py 3.16 ships it) reads a global heap collection ("GCOL", file format
spec III.E: where every variable-length string of a recording lives, its attributes among
them) by walking its objects: each object advances the walk by its 16-byte header and its
size rounded up to 8 bytes, the free-space object (index 0) by its size alone. An object
whose step is 0 (a free-space object of size 0, or a size that wraps the 64-bit sum to 0)
leaves the walk where it is, and libhdf5 spins in `H5HG__cache_heap_deserialize` forever,
holding the GIL (h5py does not release it): no timeout, thread or signal handler in the same
process can end it. One byte inserted into a collection (found by fuzzing) lets the walk
step into the zero padding behind the last object: a free-space object of size 0. A
collection that runs past the end of a file opened by SWMR (a writer died with it open, its
tail lost) reads as zeros there: the same loop.

`check_global_heaps` walks every collection libhdf5 could read as libhdf5 does and rejects
a file whose walk would stall or leave its collection. A candidate is every "GCOL" signature
with version 1 whose collection fits the file's address space (libhdf5 refuses to read one
that does not), so recorded samples that happen to spell the signature are passed over: to
be taken for a collection they would also need a size below the file's, i.e. a neighbouring
float64 below 1e-290. The scan reads the file once by `os.pread` in blocks of `BLOCK_BYTES`,
not through mmap: a writer's HDF5 truncates its file when it closes it (the disk reserve
given back), and a mapped page past the new end kills the reader with SIGBUS. A child
process with a time limit would bound any hang, but costs an interpreter with h5py
(0.6-0.7 s) on every open and cannot tell a slow disk from a loop; the walk costs 0.2 ms
on a small recording and says where the damage is.
"""

from __future__ import annotations

import os
from pathlib import Path

SIGNATURE = b"\x89HDF\r\n\x1a\n"
"""The superblock's signature, at byte 0, 512, 1024, 2048, … (spec II.A)."""

GLOBAL_HEAP = b"GCOL\x01"
"""A global heap collection's signature and version (spec III.E)."""

ALIGNMENT = 8
"""Global heap objects are padded to this many bytes."""

WORD = 1 << 64
"""libhdf5 adds sizes in 64-bit words (size_t): sums wrap modulo this."""

BLOCK_BYTES = 1 << 20
"""The signature scan reads this many bytes (1 MiB) at a time: as fast as mmap was here
(0.25 vs 0.30 s for 208 MB from the page cache, loaded 2-core VM), 4 MiB and more slower."""


class _FileBytes:
    """The bytes of an open file read on demand by `os.pread`: slices, `find` and the size
    at opening; bytes past the file's end (it may shrink meanwhile) read as absent."""

    def __init__(self, fd: int) -> None:
        self._fd = fd
        self._size = os.fstat(fd).st_size

    def __len__(self) -> int:
        return self._size

    def __getitem__(self, span: slice) -> bytes:
        start, stop = span.start, min(span.stop, self._size)
        return os.pread(self._fd, stop - start, start) if stop > start else b""

    def find(self, needle: bytes, start: int = 0) -> int:
        """The offset of the first `needle` at or after `start`, -1 if there is none."""
        while start < self._size:
            block = self[start:start + BLOCK_BYTES + len(needle) - 1]
            if (found := block.find(needle)) >= 0:
                return start + found
            start += BLOCK_BYTES
        return -1


class DamagedHdf5(OSError):
    """A file libhdf5 would loop on or read outside its structures; the message says where."""


def check_global_heaps(path: Path) -> None:
    """Raise DamagedHdf5 if a global heap collection of the HDF5 file at `path` would make
    libhdf5's object walk stall or leave the collection; a file that is not HDF5 (no
    superblock) or is empty passes (h5py rejects it itself)."""
    with path.open("rb") as file:
        data = _FileBytes(file.fileno())
        superblock = _superblock(data)
        if superblock is None:
            return
        lengths, end = superblock
        start = data.find(GLOBAL_HEAP)
        while start >= 0:
            _walk(data, start, lengths, end)
            start = data.find(GLOBAL_HEAP, start + 1)


def _superblock(data: _FileBytes) -> tuple[int, int] | None:
    """(bytes per length, file offset up to which libhdf5 may read: the end-of-file address
    counted from the signature, so at least that before a userblock too) of the first
    superblock, or None (no signature, an unknown version or field size)."""
    start = 0
    while start + 16 <= len(data) and data[start:start + 8] != SIGNATURE:
        start = 512 if start == 0 else 2 * start
    if start + 16 > len(data):
        return None
    head = data[start + 8:start + 15].ljust(7, b"\0")  # version, sizes at 1-2 (v0/1: 5-6)
    version = head[0]
    if version > 3:
        return None
    offsets, lengths = (head[1], head[2]) if version >= 2 else (head[5], head[6])
    if offsets not in (2, 4, 8, 16, 32) or lengths not in (2, 4, 8, 16, 32):
        return None
    eoa_at = {0: 24, 1: 28}.get(version, 12) + 2 * offsets  # after base and one address
    return lengths, start + _number(data, start + eoa_at, offsets)


def _walk(data: _FileBytes, start: int, lengths: int, end: int) -> None:
    """Walk the collection at byte `start` as `H5HG__cache_heap_deserialize` does (bytes past
    the file's end read as zeros, as libhdf5's sec2 driver reads them)."""
    size = _number(data, start + 8, lengths)
    if start + size > end:
        return  # libhdf5 refuses the read: "addr overflow"
    header = 8 + lengths  # index 2, references 2, reserved 4, size
    at = _aligned(8 + lengths)
    while at < size and at + header <= size:
        index = _number(data, start + at, 2)
        object_size = _number(data, start + at + 8, lengths)
        step = object_size if index == 0 else (header + _aligned(object_size)) % WORD
        where = f"global heap at byte {start}: object {index} at byte {at}" + \
            (" (past the file's end: zeros)" if start + at >= len(data) else "")
        if step == 0:
            raise DamagedHdf5(f"{where} has size {object_size}: a step of 0, HDF5 would "
                              f"read it forever")
        if step > size - at or (index and object_size > size - at - header):
            raise DamagedHdf5(f"{where} has size {object_size}, past the collection's "
                              f"{size} bytes")
        at += step


def _aligned(size: int) -> int:
    """`size` rounded up to ALIGNMENT as libhdf5's H5HG_ALIGN computes it (64-bit)."""
    return (size + ALIGNMENT - 1) % WORD // ALIGNMENT * ALIGNMENT


def _number(data: _FileBytes, at: int, width: int) -> int:
    """The little-endian unsigned number of `width` bytes at `at` (modulo 2⁶⁴, as libhdf5
    decodes it), bytes past the end of `data` read as zeros."""
    return int.from_bytes(data[at:at + width], "little") % WORD
