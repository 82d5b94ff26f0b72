"""A headless Chromium driven over the DevTools protocol, for the viewer and report tests (and docs screenshots).

Debian's chromium-headless-shell renders WebGL offline with SwiftShader. The browser runs in its own process group,
which close() kills whole (the /usr/bin wrapper does not exec, so killing one process would leave the browser).
"""

from __future__ import annotations

import atexit
import base64
import ctypes
import itertools
import json
import os
import re
import shutil
import signal
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

CANDIDATES = ("/usr/lib/chromium/chromium-headless-shell", "chromium-headless-shell", "chromium", "google-chrome")


def find_browser() -> str | None:
    for name in CANDIDATES:
        path = name if os.path.isabs(name) and os.access(name, os.X_OK) else shutil.which(name)
        if path:
            return path
    return None


def _die_with_parent() -> None:
    """In the child before exec: Linux kills the browser when the Python process dies, however it dies (its own
    helper processes then exit as their browser is gone)."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


class Browser:
    def __init__(self, width: int = 800, height: int = 600):
        from websockets.sync.client import connect

        executable = find_browser()
        if executable is None:
            raise RuntimeError("no headless Chromium found (apt-get install chromium-headless-shell)")
        self.profile = tempfile.mkdtemp(prefix="mcsplat-chromium-")
        self.process = subprocess.Popen(
            [executable, "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
             "--remote-debugging-port=0", "--remote-debugging-address=127.0.0.1", f"--user-data-dir={self.profile}",
             f"--window-size={width},{height}", "--no-first-run", "--hide-scrollbars", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
            preexec_fn=_die_with_parent)
        atexit.register(self.close)
        try:
            port = self._devtools_port()
            pages = [t for t in self._json(port, "list") if t["type"] == "page"]
            self.socket = connect(pages[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=20)
        except Exception:
            self.close()
            raise
        self.ids = itertools.count(1)
        self.events: list[dict] = []

    def _devtools_port(self) -> int:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            line = self.process.stderr.readline()
            found = re.search(r"DevTools listening on ws://[^:]+:(\d+)/", line)
            if found:
                return int(found.group(1))
            if not line and self.process.poll() is not None:
                break
        raise RuntimeError("headless Chromium did not start its DevTools server")

    @staticmethod
    def _json(port: int, path: str):
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/{path}", timeout=10) as response:
            return json.loads(response.read())

    def call(self, method: str, timeout: float = 60, **params) -> dict:
        """Send one DevTools command and wait for its answer (events arriving meanwhile are kept in .events)."""
        message_id = next(self.ids)
        self.socket.send(json.dumps({"id": message_id, "method": method, "params": params}))
        deadline = time.monotonic() + timeout
        while True:
            message = json.loads(self.socket.recv(timeout=max(0.1, deadline - time.monotonic())))
            if message.get("id") == message_id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message.get("result", {})
            self.events.append(message)

    def evaluate(self, expression: str, timeout: float = 60):
        result = self.call("Runtime.evaluate", timeout=timeout, expression=expression, awaitPromise=True,
                           returnByValue=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"{expression}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def wait_for(self, expression: str, timeout: float = 60, interval: float = 0.25):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                value = self.evaluate(expression)
            except RuntimeError:  # the page is still loading (no document.body yet, ...)
                value = None
            if value:
                return value
            time.sleep(interval)
        raise TimeoutError(f"waited {timeout} s for {expression}")

    def screenshot(self, path: Path) -> None:
        data = self.call("Page.captureScreenshot", format="png")["data"]
        path.write_bytes(base64.b64decode(data))

    def requested_urls(self) -> list[str]:
        return [e["params"]["request"]["url"] for e in self.events if e.get("method") == "Network.requestWillBeSent"]

    def close(self) -> None:
        atexit.unregister(self.close)
        socket = getattr(self, "socket", None)
        if socket is not None:
            socket.close()
        if self.process.poll() is None:
            try:
                os.killpg(self.process.pid, signal.SIGKILL)  # the whole group: renderer, GPU process, ...
            except ProcessLookupError:
                pass
        self.process.wait(timeout=10)
        if not self.process.stderr.closed:
            self.process.stderr.close()
        shutil.rmtree(self.profile, ignore_errors=True)
