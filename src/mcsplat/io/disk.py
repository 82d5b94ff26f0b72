"""One-line errors for writes the file system refuses: a full disk (or quota), a read-only file system, no permission.

Nothing is lost when that happens (every output is written beside its final name first, see atomic.py), but a
traceback does not say which folder is full or how much room the write needed; these errors do.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
from pathlib import Path
from typing import Iterator

from ..errors import MCSplatError

NO_SPACE = {errno.ENOSPC, errno.EDQUOT}
NEARLY_FULL = 16 * 2**20  # bytes: less free than this after a failed write, and the disk is what failed


def free_bytes(folder: str | os.PathLike) -> int | None:
    """Free bytes for this user on `folder`'s file system (its nearest existing parent's), or None if unknown."""
    folder = Path(folder)
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return None


def size_text(count: float) -> str:
    for unit in ("bytes", "KB", "MB", "GB"):
        if count < 1000 or unit == "GB":
            return f"{count:,.0f} {unit}" if unit == "bytes" else f"{count:,.1f} {unit}"
        count /= 1000
    return ""


def no_space(folder: str | os.PathLike, needed: str = "", freed: int = 0) -> MCSplatError:
    """`needed`: what the write needed, in words ("about 1.2 GB"; empty when unknown); `freed`: bytes that the
    failed command is about to free (its partial work), counted as free."""
    free = free_bytes(folder)
    amounts = ([f"{needed} needed"] if needed else []) + ([f"{size_text(free + freed)} free"] if free is not None
                                                         else [])
    return MCSplatError(f"no space left on the device of {folder} ({', '.join(amounts)}); free some space (or "
                        f"write elsewhere) and run again")


def refused_write(error: BaseException, folder: str | os.PathLike, needed: int | None = None,
                  written: int = 0) -> MCSplatError | None:
    """The one-line error for a write into `folder` that failed with `error`, or None when the file system did not
    refuse it. `needed`: the bytes the write takes, where known; `written`: how many it wrote before it failed.

    Some writers (torch.save) report a full disk without an errno: their failure counts as one when the folder has
    less free space than the write needed (or almost none)."""
    if isinstance(error, MCSplatError):
        return None  # already says what is wrong
    code = getattr(error, "errno", None)
    if code == errno.EROFS:
        return MCSplatError(f"cannot write to {folder}: it is on a read-only file system; write elsewhere")
    if code in (errno.EACCES, errno.EPERM):
        return MCSplatError(f"cannot write to {folder}: permission denied; write elsewhere or change its "
                            f"permissions")
    amount = f"about {size_text(needed)}" if needed else f"more than {size_text(written)}" if written else ""
    if code in NO_SPACE:
        return no_space(folder, amount)
    if isinstance(error, OSError) or not isinstance(error, Exception):
        return None
    free = free_bytes(folder)
    if free is not None and free < max(needed or 0, NEARLY_FULL):
        return no_space(folder, amount)
    return None


@contextlib.contextmanager
def writing_into(folder: str | os.PathLike, needed: int | None = None) -> Iterator[None]:
    """Turn an OSError of a write refused by the file system inside this block into refused_write's one-line
    error."""
    try:
        yield
    except OSError as error:
        problem = refused_write(error, folder, needed)
        if problem is None:
            raise
        raise problem from None
