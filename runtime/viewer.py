"""`nehad view`: a scene in the browser, orbited with the mouse and scrubbed in time
(docs/view.md). Torch-free: the page is served by viser (the `view` extra), the deformation is
evaluated by the scene (runtime/scene.py), the pictures are drawn by nehad's rasterizer.

Two drawing modes, switchable in the page:

* ``server``: this process draws each view with the rasterizer every command uses (what
  `nehad render` writes for that camera and time) and sends it as the page's background image,
  for browsers that cannot draw the splats themselves;
* ``browser``: the page draws the Gaussians with viser's WebGL splat renderer, fed the deformed
  Gaussians at the slider's time (base colour only: the SH degree-0 term, no view dependence).

The deformation is evaluated once per time (:class:`TimeCache`): moving the camera re-draws,
it does not re-deform. Requests are coalesced: while a picture is drawn, only the newest camera
of each browser tab waits, so a fast drag never builds a queue.
"""

from __future__ import annotations

import errno
import math
import socket
import threading
import time as _time
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from .cameras import Camera
from .errors import InputProblem

MODES = ("server", "browser")


class ViewerError(InputProblem):
    """The viewer cannot start as asked (a port in use, viser missing); the message says why."""


# ---------------------------------------------------------------------------------------------
# cameras: viser's (OpenCV axes, camera-to-world rotation, vertical field of view) <-> ours;
# quaternions through viser.transforms (viser is this module's dependency anyway)


def camera_from_view(position, wxyz, fov_y: float, width: int, height: int,
                     time: float | None = None) -> Camera:
    """Our camera for a browser view: OpenCV axes (as viser), camera-to-world rotation `wxyz`,
    vertical field of view `fov_y` (radians), square pixels, centred principal point."""
    from viser import transforms

    c2w = np.eye(4)
    c2w[:3, :3] = transforms.SO3(np.asarray(wxyz, np.float64)).as_matrix()
    c2w[:3, 3] = np.asarray(position, np.float64)
    fy = 0.5 * height / math.tan(0.5 * fov_y)
    return Camera(int(width), int(height), fy, fy, 0.5 * width, 0.5 * height,
                  np.linalg.inv(c2w), time, "view")


def view_of_camera(camera: Camera) -> tuple[np.ndarray, np.ndarray, float]:
    """(position, wxyz, vertical fov) that show `camera`'s view in the browser."""
    from viser import transforms

    c2w = np.linalg.inv(np.asarray(camera.world_to_camera, np.float64))
    fov_y = 2.0 * math.atan(0.5 * camera.height / camera.fy)
    return c2w[:3, 3].copy(), transforms.SO3.from_matrix(c2w[:3, :3]).wxyz, fov_y


def splat_arrays(cloud):
    """(centres, covariances, rgb, opacity) of a GaussianCloud for viser's splat renderer:
    Sigma = R S S^T R^T, and the SH degree-0 colour 0.5 + C0 dc (no view dependence)."""
    from viser import transforms

    q = cloud.quats.astype(np.float64)
    r = transforms.SO3(q / np.linalg.norm(q, axis=1, keepdims=True)).as_matrix()
    rs = r * cloud.scales.astype(np.float64)[:, None, :]
    cov = np.einsum("nij,nkj->nik", rs, rs).astype(np.float32)
    rgb = cloud.base_rgb().astype(np.float32)
    return cloud.means.astype(np.float32), cov, rgb, cloud.opacities.reshape(-1, 1)


# ---------------------------------------------------------------------------------------------
# the deformed Gaussians, once per time


class TimeCache:
    """The scene's Gaussians at the last `size` times asked for (a time is rounded to 1e-6)."""

    def __init__(self, scene, size: int = 8):
        self.scene, self.size = scene, size
        self.entries: OrderedDict = OrderedDict()
        self.evaluations = 0  # how many times the deformation ran
        self.lock = threading.Lock()

    def gaussians(self, t: float | None):
        key = None if t is None or not self.scene.dynamic else round(float(t), 6)
        with self.lock:
            if key in self.entries:
                self.entries.move_to_end(key)
                return self.entries[key]
            cloud = self.scene.gaussians(key)
            self.evaluations += 1
            self.entries[key] = cloud
            while len(self.entries) > self.size:
                self.entries.popitem(last=False)
            return cloud


# ---------------------------------------------------------------------------------------------
# the server


def check_port(host: str, port: int) -> None:
    """ViewerError when `port` cannot be bound on `host` (viser would silently take the next
    one, and the printed address would not be the one asked for)."""
    family, address = resolve_host(host)
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((address, port))  # port 0 too: the host must be one of this machine's
        except OSError as e:
            if port == 0 or e.errno == errno.EADDRNOTAVAIL:
                raise ViewerError(f"{{host}} {host}: cannot listen on it ({e.strerror or e}); "
                                  f"give an address of this machine (127.0.0.1, 0.0.0.0)",
                                  "host") from None
            raise ViewerError(f"{{port}} {port}: cannot listen on {host}:{port} "
                              f"({e.strerror or e}); is another server using it?", "port") from None


#: seconds a host name may take to resolve before `nehad view` gives up on it
RESOLVE_SECONDS = 5.0


def resolve_host(host: str, timeout: float = RESOLVE_SECONDS) -> tuple[int, str]:
    """(address family, numeric address) of `host`; ViewerError when it is not an address and
    does not resolve within `timeout` seconds (issue 26: ``--host 999.999.999.999`` was handed
    to the resolver and then to the server thread, which failed without a word)."""
    import ipaddress
    import threading

    text = str(host).strip()
    try:
        ip = ipaddress.ip_address(text.strip("[]"))
    except ValueError:
        ip = None
    if ip is not None:
        return (socket.AF_INET6 if ip.version == 6 else socket.AF_INET), str(ip)
    if not text or all(c.isdigit() or c == "." for c in text):
        # dotted digits that are not an IPv4 address (999.999.999.999, 1.2.3): a typo, not a name
        raise ViewerError(f"{{host}} {host!r}: not a valid IP address", "host")
    found: list = []

    def lookup():
        try:
            found.append(socket.getaddrinfo(text, None, type=socket.SOCK_STREAM))
        except OSError as e:
            found.append(e)

    worker = threading.Thread(target=lookup, name="nehad-resolve", daemon=True)
    worker.start()
    worker.join(timeout)
    if not found:
        raise ViewerError(f"{{host}} {host}: the name did not resolve within {timeout:g} s; "
                          f"give an IP address", "host")
    if isinstance(found[0], OSError) or not found[0]:
        why = found[0] if isinstance(found[0], OSError) else "no address"
        raise ViewerError(f"{{host}} {host}: unknown host ({getattr(why, 'strerror', None) or why})",
                          "host")
    family, _, _, _, sockaddr = found[0][0]
    return family, sockaddr[0]


@dataclass
class FrameStats:
    """What the panel shows of the last picture."""

    seconds: float = 0.0  # deform (when not cached) + draw (+ encode in server mode)
    gaussians: int = 0
    time: float | None = None


class Viewer:
    """A viser server showing `scenes` (layer count -> Scene; key None: all layers).

    `cameras`: the dataset cameras the page offers to jump to (the first is where a new tab
    starts; default: the cameras the scene comes with, Scene.cameras). `mode`: "server" or "browser" (module doc).
    """

    def __init__(self, scenes: dict, cameras=(), mode: str = "server", background=None,
                 host: str = "127.0.0.1", port: int = 8080, image_format: str = "png"):
        if mode not in MODES:
            raise ViewerError(f"{{mode}} {mode!r}: expected one of {', '.join(MODES)}", "mode")
        self.scenes = scenes
        self.lod = None if None in scenes else max(k for k in scenes)
        self.scene = scenes[self.lod]
        self.caches = {k: TimeCache(s) for k, s in scenes.items()}
        self.cameras = list(cameras) or self.scene.cameras()
        self.mode = mode
        self.background = tuple(background or self.scene.default_background)
        self.host, self.port, self.image_format = host, port, image_format
        lo, hi = self.scene.time_range
        self.time = float(lo) if self.scene.dynamic else None
        self.playing = False
        self.speed = 0.25  # of the time range per second
        self.stats = FrameStats()
        self._draw_lock = threading.Lock()  # one rasterization at a time (Numba's layers)
        self._pending: dict = {}  # client id -> newest view to draw
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.server = None
        self._splats = None
        self.images_sent = 0
        self.last_image: np.ndarray | None = None

    # -- public ----------------------------------------------------------------------------
    def start(self) -> str:
        """Start serving; returns the address to open."""
        try:
            import viser
        except ImportError:
            raise ViewerError("viewing needs viser, which is not installed: pip install -e "
                              "'.[view]'") from None
        check_port(self.host, self.port)
        self.server = viser.ViserServer(host=self.host, port=self.port, verbose=False)
        self.server.gui.configure_theme(control_layout="floating", show_logo=False,
                                        show_share_button=False)
        self.server.scene.set_up_direction(self._up())
        self._build_gui()
        self.server.on_client_connect(self._on_connect)
        threading.Thread(target=self._draw_loop, name="nehad-view-draw", daemon=True).start()
        threading.Thread(target=self._play_loop, name="nehad-view-play", daemon=True).start()
        if self.mode == "browser":
            self._send_splats()
        host = f"[{self.host}]" if ":" in self.host else self.host  # an IPv6 address
        return f"http://{host}:{self.server.get_port()}"

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self.server is not None:
            self.server.stop()

    def set_time(self, t: float) -> None:
        """Move the time slider (as the page does)."""
        self.gui_time.value = float(t)

    # -- building the page -------------------------------------------------------------------
    def _up(self):
        if self.cameras:
            c2w = np.linalg.inv(np.asarray(self.cameras[0].world_to_camera, np.float64))
            up = -c2w[:3, 1]  # OpenCV: image up is -y
            k = int(np.argmax(np.abs(up)))
            axis = np.zeros(3)
            axis[k] = np.sign(up[k])
            return tuple(axis)
        return (0.0, 0.0, 1.0)

    def _build_gui(self) -> None:
        gui = self.server.gui
        lo, hi = self.scene.time_range
        self.gui_info = gui.add_markdown(self._info_text())
        self.gui_mode = gui.add_dropdown("Drawing", MODES, initial_value=self.mode)
        self.gui_time = gui.add_slider("Time", min=float(lo), max=float(hi),
                                       step=max((hi - lo) / 1000.0, 1e-6),
                                       initial_value=float(self.time if self.time is not None
                                                           else lo),
                                       disabled=not self.scene.dynamic)
        self.gui_play = gui.add_checkbox("Play", initial_value=False,
                                         disabled=not self.scene.dynamic)
        self.gui_speed = gui.add_slider("Speed (range/s)", min=0.02, max=2.0, step=0.01,
                                        initial_value=self.speed)
        levels = ["all"] + [str(k) for k in sorted(k for k in self.scenes if k is not None)]
        self.gui_lod = gui.add_dropdown("Layers", levels,
                                        initial_value="all" if self.lod is None else str(self.lod),
                                        disabled=len(self.scenes) < 2)
        self.gui_background = gui.add_rgb("Background", tuple(
            int(round(255 * c)) for c in self.background))
        names = [c.name or f"camera {k}" for k, c in enumerate(self.cameras)]
        names = [f"{k}: {n}" for k, n in enumerate(names)]
        self.gui_camera = gui.add_dropdown("Camera", names or ["(none)"],
                                           initial_value=names[0] if names else "(none)",
                                           disabled=not names)
        self._camera_names = names

        @self.gui_time.on_update
        def _(_event):
            self.time = float(self.gui_time.value) if self.scene.dynamic else None
            self._changed()

        @self.gui_play.on_update
        def _(_event):
            self.playing = bool(self.gui_play.value)

        @self.gui_speed.on_update
        def _(_event):
            self.speed = float(self.gui_speed.value)

        @self.gui_mode.on_update
        def _(_event):
            self.mode = self.gui_mode.value
            if self.mode == "browser":
                self.server.scene.set_background_image(None)
            else:
                self._remove_splats()
            self._changed()

        @self.gui_lod.on_update
        def _(_event):
            v = self.gui_lod.value
            self.lod = None if v == "all" else int(v)
            self.scene = self.scenes[self.lod]
            self._changed()

        @self.gui_background.on_update
        def _(_event):
            self.background = tuple(c / 255.0 for c in self.gui_background.value)
            self._changed()

        @self.gui_camera.on_update
        def _(event):
            if self._camera_names:
                k = self._camera_names.index(self.gui_camera.value)
                targets = [event.client] if event.client is not None else \
                    list(self.server.get_clients().values())
                for client in targets:
                    self._jump(client, self.cameras[k])

    def _info_text(self) -> str:
        s = self.stats
        t = "static" if s.time is None else f"t = {s.time:.3f}"
        return (f"**{self.scene.describe()}**  \n{t} · {s.gaussians} Gaussians · "
                f"frame {1000 * s.seconds:.1f} ms ({self.mode})")

    # -- events --------------------------------------------------------------------------------
    def _on_connect(self, client) -> None:
        if self.cameras:
            self._jump(client, self.cameras[0])

        @client.camera.on_update
        def _(_camera):
            self._request(client)

        self._request(client)

    def _jump(self, client, camera: Camera) -> None:
        position, wxyz, fov = view_of_camera(camera)
        with client.atomic():
            client.camera.fov = fov
            client.camera.wxyz = wxyz
            client.camera.position = position
        self._request(client)

    def _changed(self) -> None:
        """The time, layers, mode or background changed: redraw everything."""
        if self.mode == "browser":
            self._send_splats()
        for client in self.server.get_clients().values():
            self._request(client)

    def _request(self, client) -> None:
        if self.mode != "server":
            return
        self._pending[client.client_id] = client
        self._wake.set()

    # -- drawing ----------------------------------------------------------------------------
    def _draw_loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            while self._pending and not self._stop.is_set():
                _, client = self._pending.popitem()
                try:
                    self._draw_for(client)
                except Exception as e:  # a tab that closed mid-frame, a bad camera
                    print(f"nehad view: frame not drawn: {type(e).__name__}: {e}")

    def view_camera(self, client) -> Camera:
        """Our camera for what `client` shows now."""
        cam = client.camera
        return camera_from_view(cam.position, cam.wxyz, cam.fov, cam.image_width,
                                cam.image_height, self.time)

    def draw(self, camera: Camera) -> np.ndarray:
        """The server-mode picture of `camera` at the current time and layers: what
        `nehad render` draws for it (with the threads the machine's load leaves free,
        runtime/threads.py)."""
        from .raster import render

        start = _time.perf_counter()
        with self._draw_lock:
            cloud = self.caches[self.lod].gaussians(self.time)
            image = render(cloud, camera, background=self.background).rgb
        self.stats = FrameStats(_time.perf_counter() - start, len(cloud), self.time)
        return image

    def _draw_for(self, client) -> None:
        if self.mode != "server":
            return
        camera = self.view_camera(client)
        if camera.width < 1 or camera.height < 1:
            return
        start = _time.perf_counter()
        image = self.draw(camera)
        pixels = np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)
        client.scene.set_background_image(pixels, format=self.image_format)
        self.stats.seconds = _time.perf_counter() - start
        self.images_sent += 1
        self.last_image = pixels
        self.gui_info.content = self._info_text()

    def _send_splats(self) -> None:
        start = _time.perf_counter()
        cloud = self.caches[self.lod].gaussians(self.time)
        centres, cov, rgb, opacity = splat_arrays(cloud)
        self._splats = self.server.scene.add_gaussian_splats("/nehad", centres, cov, rgb,
                                                              opacity)
        self.server.scene.set_background_image(
            np.tile(np.round(np.asarray(self.background) * 255).astype(np.uint8), (8, 8, 1)),
            format="png")
        self.stats = FrameStats(_time.perf_counter() - start, len(cloud), self.time)
        self.gui_info.content = self._info_text()

    def _remove_splats(self) -> None:
        if self._splats is not None:
            self._splats.remove()
            self._splats = None

    def _play_loop(self) -> None:
        last = _time.perf_counter()
        while not self._stop.is_set():
            _time.sleep(1 / 30)
            now = _time.perf_counter()
            dt, last = now - last, now
            if self.playing and self.scene.dynamic:
                lo, hi = self.scene.time_range
                t = (self.time or lo) + self.speed * (hi - lo) * dt
                if t > hi:
                    t = lo + (t - hi)
                self.gui_time.value = float(min(max(t, lo), hi))


__all__ = ["Viewer", "ViewerError", "TimeCache", "camera_from_view", "view_of_camera",
           "splat_arrays", "check_port", "MODES"]
