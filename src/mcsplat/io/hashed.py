"""Files that carry a hash of their own bytes beside them (ENTRY.blake2b): the entries of mcsplat's caches. An entry
damaged or replaced since it was written no longer matches its hash, and is made again instead of served.

They are read only when they are regular files: a FIFO (or a device) in an entry's place would block the read
forever, or never end it.
"""

from __future__ import annotations

import errno
import hashlib
import os
import stat
from pathlib import Path
from typing import BinaryIO

from .atomic import atomic_path, atomic_write_text

SUFFIX = ".blake2b"
_BLOCK = 1 << 20


class NotARegularFile(OSError):
    """A cache file that is a FIFO, a device, a folder...: never opened for reading."""


def hash_file(entry: Path) -> Path:
    return entry.with_suffix(SUFFIX)


def open_regular(path: str | os.PathLike) -> BinaryIO:
    """`path` opened for reading, when it is a regular file; NotARegularFile otherwise. Opened without blocking and
    checked on the open file, so that no FIFO put in its place between a check and the open can block it."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise NotARegularFile(errno.EINVAL, "not a regular file", str(path))
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def feed_file(digest, path: str | os.PathLike) -> None:
    """Feed the bytes of the regular file `path` to `digest`, a block at a time."""
    with open_regular(path) as f:
        for block in iter(lambda: f.read(_BLOCK), b""):
            digest.update(block)


def content_hash(data: bytes | str | os.PathLike) -> str:
    """The hash of `data`, or of the bytes of the file at that path."""
    digest = hashlib.blake2b(digest_size=20)
    if isinstance(data, bytes):
        digest.update(data)
    else:
        feed_file(digest, data)
    return digest.hexdigest()


def _recorded_hash(entry: Path) -> str:
    with open_regular(hash_file(entry)) as f:
        return f.read(1000).decode(errors="replace")


def intact(entry: Path) -> bool:
    """Whether the entry is there with the bytes it was written with."""
    try:
        return _recorded_hash(entry) == content_hash(entry)
    except OSError:
        return False


def read_intact(entry: Path) -> bytes:
    """The entry's bytes when they are those it was written with; OSError (a NotARegularFile for a FIFO) when it
    cannot be read, ValueError when its bytes differ from them."""
    with open_regular(entry) as f:
        data = f.read()
    if _recorded_hash(entry) != content_hash(data):
        raise ValueError(f"{entry.name} is not the file written there (its bytes differ from {hash_file(entry).name})")
    return data


def write_hashed(entry: Path, data: bytes) -> None:
    """Write `data` to `entry` and its hash beside it, each atomically (the entry first: a write cut short between
    the two leaves an entry that does not match its hash, which is made again)."""
    with atomic_path(entry, size_hint=len(data)) as tmp:
        tmp.write_bytes(data)
    atomic_write_text(hash_file(entry), content_hash(data))

