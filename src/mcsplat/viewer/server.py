"""The viser server: the control panel, the training cameras as frustums, and one render thread per browser.

Each browser's thread renders with our rasterizer from that browser's camera and pushes the image as the scene's
background (JPEG). While the camera moves it renders at LOW_RES on the longest side and refines to FULL_RES once the
camera has rested for SETTLE seconds (TRAINING_RES while training runs, as the image changes with every step). Renders take the run's lock, so they happen between training steps; while
training runs they are spaced so that rendering holds the lock at most DUTY of the time (the training keeps at least
about 1 - DUTY of its speed), and never more than MAX_FPS per second.
"""

from __future__ import annotations

import threading
import time
from typing import Callable, Sequence

import numpy as np

from .access import OriginPolicy, check_listen_address, origin_checked
from .cameras import camera_from_pose, image_size, pose_of
from .modes import MODES, render_mode

LOW_RES, TRAINING_RES, FULL_RES = 320, 640, 1280  # longest image side: moving, training runs, still
SETTLE = 0.25  # seconds without camera messages before the full-resolution render
MAX_FPS = 20.0
DUTY = 0.08  # most of the time that viewer renders may hold the lock while training runs
JPEG_QUALITY_MOVING, JPEG_QUALITY_STILL = 75, 92
MAX_FRUSTUMS = 300


class ViewerServer:
    def __init__(self, host: str, port: int, *, lock, scene_radius: float, background, max_sh_degree: int,
                 training: bool, on_pause: Callable[[bool], None] | None = None, quiet: bool = False,
                 origins: Sequence[str] = ()):
        """origins: what --viewer-origin allows besides the viewer's own page (access.py)."""
        import contextlib
        import io

        import viser

        check_listen_address(host, port)
        # viser prints a banner of its own; ours is one line
        with contextlib.redirect_stdout(io.StringIO()), origin_checked(OriginPolicy(host, origins)):
            self.server = viser.ViserServer(host=host, port=port, label="mcsplat", verbose=False)
        # The share button would tunnel the scene through viser's public relay: not without being asked.
        self.server.gui.configure_theme(show_share_button=False)
        self.host, self.port = host, self.server.get_port()
        self.lock, self.scene_radius, self.background = lock, scene_radius, background
        self.model = None
        self.version = 0  # bumped whenever what the image shows changes (model, mode, SH degree)
        self.training = training  # while True and not paused, renders are rate-bounded (see DUTY)
        self.paused = False
        self.training_sh_degree = max_sh_degree
        self.initial_pose = None
        self.renderers: dict[int, ClientRenderer] = {}
        self.frustums = []
        gui = self.server.gui
        self.stats = gui.add_markdown("loading ...")
        self.pause_button = gui.add_button("Pause training", visible=training)
        self.resume_button = gui.add_button("Resume training", visible=False)
        self.mode = gui.add_dropdown("Render mode", MODES, initial_value="RGB")
        degrees = (("training",) if training else ()) + tuple(str(d) for d in range(max_sh_degree + 1))
        self.sh_degree = gui.add_dropdown("SH degree", degrees, initial_value=degrees[0] if training else degrees[-1])
        self.show_cameras = gui.add_checkbox("Training cameras", initial_value=True)

        def set_paused(paused: bool) -> None:
            self.paused = paused
            if on_pause is not None:
                on_pause(paused)
            self.touch()
            self.pause_button.visible, self.resume_button.visible = not paused, paused

        self.pause_button.on_click(lambda _: set_paused(True))
        self.resume_button.on_click(lambda _: set_paused(False))
        self.mode.on_update(lambda _: self.touch())
        self.sh_degree.on_update(lambda _: self.touch())
        self.show_cameras.on_update(lambda _: self._show_frustums(self.show_cameras.value))
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        if not quiet:
            shown = "localhost" if host in ("127.0.0.1", "localhost") else host
            print(f"mcsplat: viewer at http://{shown}:{self.port}", flush=True)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}" if self.host in ("0.0.0.0", "127.0.0.1") else \
            f"http://{self.host}:{self.port}"

    def set_model(self, model) -> None:
        self.model = model
        self.touch()

    def touch(self) -> None:
        self.version += 1
        for renderer in list(self.renderers.values()):
            renderer.wake.set()

    @property
    def training_runs(self) -> bool:
        return self.training and not self.paused

    def set_stats(self, markdown: str) -> None:
        self.stats.content = markdown

    def current_sh_degree(self) -> int:
        value = self.sh_degree.value
        return self.training_sh_degree if value == "training" else int(value)

    def add_cameras(self, cameras) -> None:
        """Frustums of the training cameras; the first one becomes the browsers' initial view."""
        step = max(1, len(cameras) // MAX_FRUSTUMS)
        for i, camera in enumerate(cameras[::step]):
            wxyz, position, fov_y, aspect = pose_of(camera)
            if self.initial_pose is None:
                self.initial_pose = (wxyz, position, fov_y)
            self.frustums.append(self.server.scene.add_camera_frustum(
                f"/cameras/{i}", fov=fov_y, aspect=aspect, scale=0.05 * self.scene_radius, color=(220, 120, 20),
                wxyz=wxyz, position=position, thickness=1.5, thickness_units="screen"))

    def _show_frustums(self, visible: bool) -> None:
        for frustum in self.frustums:
            frustum.visible = visible

    def render(self, camera, mode: str | None = None) -> np.ndarray:
        """The image the viewer shows for `camera` (under the lock)."""
        with self.lock:
            return render_mode(self.model, camera, mode or self.mode.value, self.background,
                               self.current_sh_degree(), self.scene_radius)

    def _connect(self, client) -> None:
        if self.initial_pose is not None:
            wxyz, position, fov_y = self.initial_pose
            with client.atomic():
                client.camera.fov = fov_y
                client.camera.wxyz = wxyz
                client.camera.position = position
        renderer = ClientRenderer(self, client)
        self.renderers[client.client_id] = renderer
        client.camera.on_update(lambda _: renderer.moved())
        renderer.start()

    def _disconnect(self, client) -> None:
        renderer = self.renderers.pop(client.client_id, None)
        if renderer is not None:
            renderer.stop()

    def close(self) -> None:
        for renderer in list(self.renderers.values()):
            renderer.stop()
        for renderer in list(self.renderers.values()):
            renderer.join(timeout=5)
        self.renderers.clear()
        self.server.stop()


class ClientRenderer(threading.Thread):
    """Renders for one browser whenever its camera, the model or the settings changed."""

    def __init__(self, viewer: ViewerServer, client):
        super().__init__(name=f"mcsplat-viewer-{client.client_id}", daemon=True)
        self.viewer, self.client = viewer, client
        self.wake = threading.Event()
        self.stopped = False
        self.last_move = 0.0
        self.shown = None  # (camera state, version, resolution) of the image the browser has
        self.next_allowed = 0.0
        self.frames = 0
        self.render_seconds = 0.0  # spent rendering (holding the run's lock)

    def moved(self) -> None:
        self.last_move = time.monotonic()
        self.wake.set()

    def stop(self) -> None:
        self.stopped = True
        self.wake.set()

    def run(self) -> None:
        while not self.stopped:
            self.wake.wait(timeout=SETTLE / 2)
            self.wake.clear()
            if self.stopped or self.viewer.model is None:
                continue
            camera = self.client.camera
            moving = time.monotonic() - self.last_move < SETTLE
            longest = LOW_RES if moving else TRAINING_RES if self.viewer.training_runs else FULL_RES
            width, height = image_size(camera.image_width, camera.image_height, longest)
            state = (tuple(camera.wxyz), tuple(camera.position), camera.fov, width, height, self.viewer.version)
            if state == self.shown:
                continue
            wait = self.next_allowed - time.monotonic()
            if wait > 0:
                time.sleep(wait)
                self.wake.set()  # look again: the state may have changed meanwhile
                continue
            ours = camera_from_pose(camera.wxyz, camera.position, camera.fov, width, height)
            started = time.monotonic()
            try:
                image = self.viewer.render(ours)
            except Exception as error:  # a bad camera must not kill the thread; show nothing new
                print(f"mcsplat: viewer render failed: {error}", flush=True)
                self.shown = state
                continue
            spent = time.monotonic() - started
            self.render_seconds += spent
            gap = spent * (1.0 - DUTY) / DUTY if self.viewer.training_runs else 0.0
            self.next_allowed = started + max(spent + gap, 1.0 / MAX_FPS)
            self.client.scene.set_background_image(
                image, format="jpeg", jpeg_quality=JPEG_QUALITY_MOVING if moving else JPEG_QUALITY_STILL)
            self.shown = state
            self.frames += 1
            if moving:
                self.wake.set()  # come back to refine once the camera settles
