"""An exclusive lock on a folder, held through a lock file, so that two commands never write one folder at once.

The lock is the kernel's `flock` on the lock file, not the file's existence: a process that dies, however it dies,
releases it, so a lock file left behind by a killed run is stale and simply taken over. The file holds the owner's
pid, host, command and start time for the message the next writer gets. On a file system without `flock` (some
network mounts) the pid alone decides: a lock of a process that no longer runs on this host is stale.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import socket
import time
from pathlib import Path

from ..errors import MCSplatError
from .disk import writing_into

try:
    import fcntl
except ImportError:  # Windows: no flock; the pid decides
    fcntl = None

_NO_FLOCK = {errno.ENOLCK, errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS}


class FolderBusy(MCSplatError):
    """Another live process holds the lock."""


class FolderLock:
    """`with FolderLock(path, "mcsplat train"):` holds the lock file `path` exclusively; FolderBusy when another
    process holds it. Releasing removes the file."""

    def __init__(self, path: str | os.PathLike, command: str):
        self.path = Path(path)
        self.command = command
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> FolderLock:
        if self._fd is not None:
            return self
        with writing_into(self.path.parent):
            for _ in range(10):  # a release between our open and our flock removes the file: open it again
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
                try:
                    if self._lock(fd) and self._still_the_file(fd):
                        self._fd = fd
                        self._write_owner(fd)
                        return self
                except BaseException:
                    if self._fd is not None:  # ours, but its owner could not be written (a full disk)
                        self.release()
                    else:
                        os.close(fd)
                    raise
                os.close(fd)
        raise FolderBusy(f"{self.path.parent}: could not take its lock {self.path.name}; run again")

    def release(self) -> None:
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()  # while still locked: whoever opens the path next makes a new file
        os.close(fd)

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()

    # ------------------------------------------------------------------------------------------------ helpers
    def _lock(self, fd: int) -> bool:
        """True when this process now holds `fd`'s lock; FolderBusy when a live process does."""
        if fcntl is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return True
            except BlockingIOError:
                raise self._busy(_read_owner(fd)) from None
            except OSError as error:
                if error.errno not in _NO_FLOCK:
                    raise
        owner = _read_owner(fd)
        if owner and owner.get("pid") != os.getpid() and _alive(owner):
            raise self._busy(owner)
        return True

    def _still_the_file(self, fd: int) -> bool:
        try:
            return os.stat(self.path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            return False

    def _write_owner(self, fd: int) -> None:
        owner = {"pid": os.getpid(), "host": socket.gethostname(), "command": self.command,
                 "since": time.strftime("%Y-%m-%d %H:%M:%S")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(owner) + "\n").encode(), 0)

    def _busy(self, owner: dict) -> FolderBusy:
        who = owner.get("command", "another mcsplat command")
        where = f"pid {owner.get('pid', '?')}" + (f" on {owner['host']}" if owner.get("host") != socket.gethostname()
                                                  and owner.get("host") else "")
        since = f", since {owner['since']}" if owner.get("since") else ""
        return FolderBusy(f"{self.path.parent} is in use by {who} ({where}{since}); wait for it to finish or stop it "
                          f"({self.command} would mix its files with that one's), or choose another folder")


def _read_owner(fd: int) -> dict:
    try:
        owner = json.loads(os.pread(fd, 4096, 0).decode() or "{}")
    except (OSError, ValueError):
        return {}
    return owner if isinstance(owner, dict) else {}


def _alive(owner: dict) -> bool:
    """Whether the lock's owner still runs; a lock taken on another host counts as alive (it cannot be checked)."""
    if owner.get("host") != socket.gethostname():
        return True
    try:
        os.kill(int(owner["pid"]), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, KeyError, TypeError, ValueError):
        return True
    return True
