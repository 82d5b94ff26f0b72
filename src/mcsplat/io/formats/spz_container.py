"""The two containers of Niantic's `.spz` around the same six attribute blocks (spz.py packs the blocks):

    version 3  one gzip stream of: a 16-byte header (u32 magic 0x5053474e "NGSP", u32 version 3, u32 N,
               u8 SH degree, u8 fractional bits, u8 flags, u8 reserved 0), then the blocks one after another
    version 4  uncompressed: a 32-byte header (u32 magic, u32 version 4, u32 N, u8 SH degree, u8 fractional bits,
               u8 flags, u8 number of streams S, u32 offset of the table of contents (32: no extension records),
               12 reserved zero bytes), the table of contents: S x (u64 compressed size, u64 uncompressed size),
               then the S blocks that are not empty (degree 0 has no SH block, so S = 5), each its own zstd frame
               (level 12, as Niantic's library writes them), in the order of the table

Flags: 1 = trained with antialiasing, 2 = vendor extension records between the header and the table (a reader skips
them by the table's offset). The layout follows nianticlabs/spz (README "File Format", src/cc/load-spz.cc).
"""

from __future__ import annotations

import gzip
import struct
from dataclasses import dataclass
from pathlib import Path

import zstandard

from ...errors import MCSplatError
from .common import bases_of

MAGIC = 0x5053474E
GZIP_VERSION, ZSTD_VERSION = 3, 4
VERSIONS = (GZIP_VERSION, ZSTD_VERSION)
_GZIP_HEADER = struct.Struct("<IIIBBBB")
_ZSTD_HEADER = struct.Struct("<IIIBBBBI12x")
_TOC_ENTRY = struct.Struct("<QQ")
ZSTD_LEVEL = 12
# A version-4 header may claim at most this many points per byte of file (Niantic's reader's bound: a 1024:1
# compression ratio of the 9-byte positions): a damaged count is refused before anything is allocated for it.
_MAX_POINTS_PER_BYTE = 1024 / 9


@dataclass(frozen=True)
class SpzHeader:
    version: int
    count: int
    sh_degree: int
    fractional_bits: int
    flags: int


def block_sizes(count: int, sh_degree: int) -> list[int]:
    """Bytes of positions, alphas, colours, scales, rotations and SH for `count` points."""
    return [count * 9, count, count * 3, count * 3, count * 4, count * bases_of(sh_degree) * 3]


def pack(header: SpzHeader, blocks: list[bytes]) -> bytes:
    if header.version == GZIP_VERSION:
        head = _GZIP_HEADER.pack(MAGIC, header.version, header.count, header.sh_degree, header.fractional_bits,
                                 header.flags, 0)
        return gzip.compress(head + b"".join(blocks), mtime=0)
    compressor = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
    streams = [(compressor.compress(block), len(block)) for block in blocks if block]
    head = _ZSTD_HEADER.pack(MAGIC, header.version, header.count, header.sh_degree, header.fractional_bits,
                             header.flags, len(streams), _ZSTD_HEADER.size)
    toc = b"".join(_TOC_ENTRY.pack(len(frame), size) for frame, size in streams)
    return b"".join([head, toc, *(frame for frame, _ in streams)])


def unpack(path: Path, data: bytes) -> tuple[SpzHeader, list[memoryview]]:
    """The header and the six blocks of an .spz file's bytes; a damaged file is one MCSplatError naming `path`."""
    if data[:2] == b"\x1f\x8b":
        return _unpack_gzip(path, data)
    if len(data) >= 8 and struct.unpack_from("<I", data)[0] == MAGIC:
        return _unpack_zstd(path, data)
    raise MCSplatError(f"{path}: not an .spz file (neither a gzip stream nor the NGSP header of version 4)")


def _checked_header(path: Path, fields: tuple, version: int) -> SpzHeader:
    magic, file_version, count, degree, fractional = fields[:5]
    if magic != MAGIC:
        raise MCSplatError(f"{path}: not an .spz file (magic {magic:#x})")
    if file_version != version:
        raise MCSplatError(f"{path}: .spz version {file_version} in a {'gzip' if version == 3 else 'version-4'} "
                           f"container; versions {' and '.join(map(str, VERSIONS))} are read")
    if degree > 3:
        raise MCSplatError(f"{path}: .spz of SH degree {degree}; degrees 0-3 are read")
    if not 0 < fractional < 24:
        raise MCSplatError(f"{path}: .spz header says {fractional} fractional bits of 24")
    return SpzHeader(file_version, count, degree, fractional, fields[5])


def _unpack_gzip(path: Path, data: bytes) -> tuple[SpzHeader, list[memoryview]]:
    try:
        raw = gzip.decompress(data)
    except (OSError, EOFError) as error:
        raise MCSplatError(f"{path}: a damaged gzip stream, not a readable .spz file ({error})") from None
    if len(raw) < _GZIP_HEADER.size:
        raise MCSplatError(f"{path}: too short for an .spz header")
    header = _checked_header(path, _GZIP_HEADER.unpack_from(raw), GZIP_VERSION)
    sizes = block_sizes(header.count, header.sh_degree)
    if len(raw) != _GZIP_HEADER.size + sum(sizes):
        raise MCSplatError(f"{path}: {len(raw)} bytes do not match {header.count} points of SH degree "
                           f"{header.sh_degree}")
    blocks, offset, view = [], _GZIP_HEADER.size, memoryview(raw)
    for size in sizes:
        blocks.append(view[offset:offset + size])
        offset += size
    return header, blocks


def _unpack_zstd(path: Path, data: bytes) -> tuple[SpzHeader, list[memoryview]]:
    if len(data) < _ZSTD_HEADER.size:
        raise MCSplatError(f"{path}: too short for an .spz version-4 header")
    fields = _ZSTD_HEADER.unpack_from(data)
    header = _checked_header(path, fields, ZSTD_VERSION)
    streams, toc_offset = fields[6], fields[7]
    if header.count > len(data) * _MAX_POINTS_PER_BYTE:
        raise MCSplatError(f"{path}: the header claims {header.count:,} points, more than {len(data):,} bytes can "
                           "hold; the file is damaged")
    sizes = [size for size in block_sizes(header.count, header.sh_degree) if size]
    if streams != len(sizes) or toc_offset < _ZSTD_HEADER.size:
        raise MCSplatError(f"{path}: the .spz header lists {streams} streams at offset {toc_offset}; "
                           f"{len(sizes)} at 32 or later were expected")
    start = toc_offset + streams * _TOC_ENTRY.size
    if start > len(data):
        raise MCSplatError(f"{path}: cut short inside the .spz table of streams")
    decompressor = zstandard.ZstdDecompressor()
    blocks = []
    for index, expected in enumerate(sizes):
        compressed, uncompressed = _TOC_ENTRY.unpack_from(data, toc_offset + index * _TOC_ENTRY.size)
        if uncompressed != expected:
            raise MCSplatError(f"{path}: .spz stream {index} is {uncompressed:,} bytes where {header.count:,} points "
                               f"need {expected:,}; the file is damaged")
        if start + compressed > len(data):
            raise MCSplatError(f"{path}: .spz stream {index} runs past the file's end: the file is cut short")
        try:
            block = decompressor.decompress(data[start:start + compressed], max_output_size=expected)
        except zstandard.ZstdError as error:
            raise MCSplatError(f"{path}: .spz stream {index} is a damaged zstd frame ({error})") from None
        if len(block) != expected:
            raise MCSplatError(f"{path}: .spz stream {index} holds {len(block):,} bytes, not {expected:,}")
        blocks.append(memoryview(block))
        start += compressed
    if start != len(data):
        raise MCSplatError(f"{path}: more bytes after the last .spz stream than the table lists; the file is "
                           "damaged")
    if header.sh_degree == 0:
        blocks.append(memoryview(b""))
    return header, blocks
