"""The SfM worker (worker.py) as a child process of `process`: started, watched, stopped by a signal, and its
failures turned into one line.

A child, not a thread: Ctrl-C cannot interrupt the main thread inside a long pycolmap call, and cancelling pycolmap
from another thread left its threads running into interpreter shutdown (an abort). The child ignores SIGINT and dies
with its parent; on Ctrl-C or SIGTERM the parent stops it and the partial work is thrown away with the work folder.

The child's stderr is for its progress bars: they are passed on as they come, and the rest (COLMAP's log lines, a
C++ stack dump when it aborts on a full disk) is kept back for the one-line error.
"""

from __future__ import annotations

import collections
import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Iterator

from ..errors import MCSplatError
from ..io.disk import NEARLY_FULL, free_bytes, no_space, size_text

PROGRESS_BARS = ("features", "matching", "mapping")  # the worker's tqdm descriptions (sfm.py)
_SEGMENT = re.compile(rb"[^\r\n]*(?:\r\n|\r|\n)")


def run_worker(work: Path, job: dict, space_needed: int) -> dict:
    """Run the worker on `job` (written to work/job.json) and return what it reports (work/result.json).
    `space_needed`: about how many bytes the work takes on disk, for the message when the disk fills up."""
    (work / "job.json").write_text(json.dumps({**job, "parent": os.getpid()}))
    child = subprocess.Popen([sys.executable, "-m", "mcsplat.capture.worker", str(work)], stderr=subprocess.PIPE)
    output = WorkerOutput(child.stderr)
    output.start()
    try:
        child.wait()
    except KeyboardInterrupt:
        child.terminate()
        child.wait()
        raise MCSplatError("interrupted: no scene was written (the partial work is removed)") from None
    finally:
        output.join(timeout=10)
    try:
        result = json.loads((work / "result.json").read_text())
    except (OSError, ValueError):  # not written, or cut short by a full disk
        result = {}
    if "error" in result:  # a problem with the input, which the worker explained
        raise MCSplatError(result["error"])
    if "crash" in result or not result:
        free = free_bytes(work)
        if free is not None and free < NEARLY_FULL:
            partial = sum(path.stat().st_size for path in work.rglob("*") if path.is_file())
            raise no_space(work.parent, f"about {size_text(space_needed)}", freed=partial)
        detail = result.get("crash") or output.last_line() or f"exit code {child.returncode}"
        raise MCSplatError(f"structure from motion stopped unexpectedly ({detail}); run again, or with --threads 1 "
                           "if it keeps failing")
    return result


class WorkerOutput(threading.Thread):
    """Reads the child's stderr: progress bars go on to ours as they come, every other line is kept (the last few)."""

    def __init__(self, stream):
        super().__init__(name="mcsplat-process-output", daemon=True)
        self.stream = stream
        self.kept: collections.deque[str] = collections.deque(maxlen=20)

    def run(self) -> None:
        pending = b""
        for chunk in iter(lambda: os.read(self.stream.fileno(), 1 << 14), b""):
            pending += chunk
            end = 0
            for match in _SEGMENT.finditer(pending):
                self._take(match.group().decode(errors="replace"))
                end = match.end()
            pending = pending[end:]
            if pending.startswith(tuple(bar.encode() for bar in PROGRESS_BARS)):  # a bar's update: show it now
                self._take(pending.decode(errors="replace"))
                pending = b""
        if pending:
            self._take(pending.decode(errors="replace"))

    def _take(self, segment: str) -> None:
        text = segment.strip()
        if not text or text.startswith(PROGRESS_BARS):
            sys.stderr.write(segment)
            sys.stderr.flush()
        else:
            self.kept.append(text)

    def last_line(self) -> str:
        """The last line that says something (not a stack frame), shortened."""
        for line in reversed(self.kept):
            if not line.startswith(("@", "*", "PC:", "File ", "Traceback")):
                return line[:200]
        return ""


@contextlib.contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM and SIGHUP (kill, timeout, a closed terminal) end `process` as Ctrl-C does: the SfM child is stopped
    and the partial work removed, instead of both being left behind by a parent that vanished."""
    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = {}
    try:
        for number in (signal.SIGTERM, signal.SIGHUP):
            previous[number] = signal.signal(number, interrupt)
    except ValueError:  # not the main thread: signals are not ours to handle
        pass
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
