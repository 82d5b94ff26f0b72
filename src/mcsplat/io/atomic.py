"""Write files so that a crash or a kill never leaves a half-written file under the final name."""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
import traceback
from pathlib import Path
from typing import Callable, Iterator

from .disk import refused_write


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, size_hint: int | None = None) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success it is fsynced and renamed over `path` in one step.

    The file gets the permissions the umask gives a new file (the temporary is made for the owner alone). A write the
    file system refuses (a full disk: `size_hint` is about how many bytes it needs) is a one-line MCSplatError."""
    target = Path(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        # Keep the real extension last: writers such as imageio choose the format from it.
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=f".tmp{target.suffix}", dir=target.parent)
    except OSError as error:
        raise (refused_write(error, target.parent, size_hint) or error) from None
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~current_umask())
        os.replace(tmp, target)
        with contextlib.suppress(OSError):  # make the rename itself durable where the OS allows it
            dir_fd = os.open(target.parent, os.O_RDONLY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)
    except Exception as error:
        written = tmp.stat().st_size if tmp.exists() else 0
        # What the temporary took is free again for the message once it is gone, and once the writer that failed
        # lets go of it (torch's stays open, held by the frames of the exceptions' tracebacks).
        cause: BaseException | None = error
        while cause is not None:
            traceback.clear_frames(cause.__traceback__)
            cause = cause.__context__
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        problem = refused_write(error, target.parent, size_hint, written)
        if problem is None:
            raise
        raise problem from None
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def current_umask() -> int:
    """The process's umask, read without changing it where Linux allows (os.umask sets it for every thread)."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def remove_stale_temporaries(path: str | os.PathLike) -> list[Path]:
    """Delete the temporary files that `atomic_path(path)` left behind when its process was killed mid-write.

    Only names of exactly the form atomic_path creates are touched (".<stem>.<8 random chars>.tmp<suffix>"), so
    nothing a user made can match. Returns the paths removed.
    """
    target = Path(path)
    pattern = re.compile(rf"\.{re.escape(target.stem)}\.[a-z0-9_]{{8}}\.tmp{re.escape(target.suffix)}")
    removed = []
    if target.parent.is_dir():
        for candidate in target.parent.iterdir():
            if pattern.fullmatch(candidate.name) and candidate.is_file():
                with contextlib.suppress(FileNotFoundError):
                    candidate.unlink()
                    removed.append(candidate)
    return removed


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path, size_hint=len(text.encode())) as tmp:
        tmp.write_text(text)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path, size_hint=len(data)) as tmp:
        tmp.write_bytes(data)


def atomic_write(path: str | os.PathLike, write: Callable[[Path], None], size_hint: int | None = None) -> None:
    """Call `write(tmp_path)`, then move the result to `path` atomically."""
    with atomic_path(path, size_hint) as tmp:
        write(tmp)
