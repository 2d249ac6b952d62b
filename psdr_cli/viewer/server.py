"""The viewer's web page: a viser server (binds ``host:port``; serves until closed) with psdr's
panels: the mesh, the cameras as frustums with their pictures, the selected view's target |
render | error strip, the loss curve, the recovered environment map and texture, a status line,
and the controls (pause, checkpoint slider, view). Reads nothing from disk and writes nothing:
its callers hand it arrays."""
from __future__ import annotations

import contextlib
import io
import threading
import time

import numpy as np
import viser
import viser.transforms as vtf

from .frustums import ViewCamera, up_direction

#: The colours the page draws with (the browser test looks for them in its screenshots).
MESH_COLOR = (235, 120, 30)
TRAIN_COLOR = (30, 90, 235)
HELD_OUT_COLOR = (220, 30, 170)
SELECTED_COLOR = (20, 200, 60)


class ViewerServer:
    """A viser server with psdr's panels; every ``show_*`` replaces what the panel showed. Safe to
    call from any one thread at a time (the live viewer's pusher, or ``psdr view``)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, title: str = "psdr", warn=print):
        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: the caller prints the address
            self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
        self.host, self.port = host, self.server.get_port()
        if port and self.port != port:
            warn(f"viewer: port {port} is in use; serving on port {self.port} instead")
        self.lock = threading.RLock()
        self.mesh = None
        self.cameras: list[ViewCamera] = []
        self.frustums = []
        self.selected = 0
        self.view_listeners = []
        self.pictures = {}
        gui = self.server.gui
        self.status = gui.add_markdown("**psdr** — waiting for data", order=0)
        self.view = gui.add_dropdown("View", ("—",), order=20)
        self.view.on_update(lambda _: self.view_index() != self.selected and self.select(self.view_index()))
        self.strip = gui.add_image(np.zeros((8, 24, 3), np.uint8), label="target | render | error", order=21)
        self.loss = gui.add_uplot(data=(np.zeros(1), np.ones(1)), series=({"label": "iteration"},
                                  {"label": "loss", "stroke": "orange", "width": 2}),
                                  scales={"x": {"time": False}, "y": {"distr": 3}}, title="loss", aspect=1.6,
                                  order=30)
        self.chamfer = None  # the Chamfer-L1 curve, made when a run has a reference mesh
        self.psnr = None  # the live render's PSNR curve, made on the first live render

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/"

    def show_status(self, text: str):
        """The status line (markdown): iteration, stage, time left, paused."""
        self.status.content = text

    def show_mesh(self, V: np.ndarray, F: np.ndarray):
        """The mesh ``(V, F)``; a mesh of the same size is updated in place, another replaces it."""
        V, F = np.asarray(V, np.float32), np.asarray(F, np.uint32)
        with self.lock:
            if self.mesh is not None and self.mesh.vertices.shape == V.shape and self.mesh.faces.shape == F.shape \
                    and np.array_equal(self.mesh.faces, F):
                self.mesh.vertices = V
                return
            if self.mesh is not None:
                self.mesh.remove()
            self.mesh = self.server.scene.add_mesh_simple("/mesh", V, F, color=MESH_COLOR, side="double")

    def show_cameras(self, cameras: list):
        """The cameras as frustums (training ones blue, held-out ones magenta, the selected one
        green) with their pictures; clicking one selects it and moves the viewpoint to it. Cameras
        already drawn with the same names and pictures are moved in place."""
        with self.lock:
            same = [c.name for c in cameras] == [c.name for c in self.cameras]
            self.cameras = list(cameras)
            if same:
                for frustum, cam in zip(self.frustums, cameras):
                    frustum.wxyz, frustum.position = pose_quaternion(cam.pose), cam.pose[:3, 3]
                return
            for frustum in self.frustums:
                frustum.remove()
            scale = frustum_scale(cameras)
            self.frustums = [self.add_frustum(i, cam, scale) for i, cam in enumerate(cameras)]
            self.view.options = tuple(camera_label(i, c) for i, c in enumerate(cameras)) or ("—",)
            self.server.scene.set_up_direction(tuple(up_direction(cameras)))
            self.overview(cameras)
            if cameras:
                self.select(min(self.selected, len(cameras) - 1))

    def overview(self, cameras: list):
        """The viewpoint a page opens with (and that of the pages open now): between the first two
        cameras, farther out and above, looking at where the cameras look (the object)."""
        if not cameras:
            return
        up = up_direction(cameras)
        centre = camera_focus(cameras)
        between = np.mean([c.pose[:3, 3] for c in cameras[:2]], axis=0) - centre
        distance = np.linalg.norm(cameras[0].pose[:3, 3] - centre)
        side = between / max(np.linalg.norm(between), 1e-9)
        position = centre + side * 1.5 * distance + up * 0.5 * distance
        initial = self.server.initial_camera
        initial.position, initial.look_at, initial.up = position, centre, up
        for client in self.server.get_clients().values():
            with client.atomic():
                client.camera.up_direction = up
                client.camera.position = position
                client.camera.look_at = centre

    def add_frustum(self, i: int, cam: ViewCamera, scale: float):
        frustum = self.server.scene.add_camera_frustum(
            f"/cameras/{i:03d}", fov=cam.fov, aspect=cam.aspect, scale=scale, thickness=0.06 * scale,
            color=self.camera_color(i, cam), image=cam.image, wxyz=pose_quaternion(cam.pose), position=cam.pose[:3, 3])
        frustum.on_click(lambda event, i=i: self.snap_to(event.client, i))
        return frustum

    def camera_color(self, i: int, cam: ViewCamera) -> tuple:
        if i == self.selected:
            return SELECTED_COLOR
        return HELD_OUT_COLOR if cam.held_out else TRAIN_COLOR

    def view_index(self) -> int:
        labels = list(self.view.options)
        return labels.index(self.view.value) if self.view.value in labels and self.cameras else 0

    def select(self, i: int):
        """Make camera ``i`` the selected view: its frustum green, the dropdown, the listeners told."""
        with self.lock:
            if not self.cameras:
                return
            self.selected = i
            for j, (frustum, cam) in enumerate(zip(self.frustums, self.cameras)):
                frustum.color = self.camera_color(j, cam)
            label = camera_label(i, self.cameras[i])
            if self.view.value != label:
                self.view.value = label
        for listener in self.view_listeners:
            listener(i)

    def on_view(self, listener):
        """Call ``listener(view)`` whenever the selected view changes."""
        self.view_listeners.append(listener)

    def snap_to(self, client, i: int):
        """Select camera ``i`` and put ``client``'s viewpoint at it, looking along its axis."""
        self.select(i)
        pose = self.cameras[i].pose
        distance = max(np.linalg.norm(pose[:3, 3]), 1e-3)
        with client.atomic():
            client.camera.position = pose[:3, 3]
            client.camera.look_at = pose[:3, 3] + pose[:3, 2] * distance
            client.camera.up_direction = -pose[:3, 1]
            client.camera.fov = self.cameras[i].fov

    def show_strip(self, image: np.ndarray | None, caption: str):
        """The selected view's target | render | error strip (8-bit RGB), or a blank with ``caption``."""
        self.strip.image = image if image is not None else np.full((8, 24, 3), 40, np.uint8)
        self.strip.label = caption

    def show_losses(self, iterations, losses):
        """The loss curve (log scale)."""
        if len(iterations) == 0:
            return
        self.loss.data = (np.asarray(iterations, np.float64), np.maximum(np.asarray(losses, np.float64), 1e-12))

    def show_chamfer(self, iterations, values):
        """The Chamfer-L1 curve against the run's reference mesh (made on first use)."""
        if len(iterations) == 0:
            return
        data = (np.asarray(iterations, np.float64), np.asarray(values, np.float64))
        if self.chamfer is None:
            self.chamfer = self.server.gui.add_uplot(
                data=data, series=({"label": "iteration"}, {"label": "Chamfer-L1", "stroke": "teal", "width": 2}),
                scales={"x": {"time": False}, "y": {"distr": 3}}, title="Chamfer-L1 to the reference", aspect=1.6,
                order=31)
        else:
            self.chamfer.data = data

    def show_psnr(self, iterations, values):
        """The PSNR of each live render against its target (the view selected at the time)."""
        data = (np.asarray(iterations, np.float64), np.minimum(np.asarray(values, np.float64), 99.0))
        if self.psnr is None:
            self.psnr = self.server.gui.add_uplot(
                data=data, series=({"label": "iteration"}, {"label": "PSNR (dB)", "stroke": "purple", "width": 2}),
                scales={"x": {"time": False}}, title="PSNR of the selected view's live render", aspect=1.6,
                order=32)
        else:
            self.psnr.data = data

    def show_picture(self, name: str, image: np.ndarray | None):
        """A named image panel (the recovered environment map, the texture), created on first use."""
        if image is None:
            return
        if name in self.pictures:
            self.pictures[name].image = image
        else:
            self.pictures[name] = self.server.gui.add_image(image, label=name, order=40 + len(self.pictures))

    def close(self):
        """Stop serving (the clients see the page disconnect)."""
        with contextlib.redirect_stdout(io.StringIO()):  # viser's "server stopped"
            self.server.stop()
            time.sleep(0.1)


def pose_quaternion(pose: np.ndarray) -> np.ndarray:
    """wxyz of the rotation of a camera-to-world ``pose`` (made orthonormal first)."""
    U, _, Vt = np.linalg.svd(pose[:3, :3])
    R = U @ Vt
    return vtf.SO3.from_matrix(R).wxyz


def frustum_scale(cameras: list) -> float:
    """Frustum size: a tenth of the cameras' mean distance from their centre (0.1 for one camera)."""
    if len(cameras) < 2:
        return 0.1
    origins = np.array([c.pose[:3, 3] for c in cameras])
    return float(0.12 * np.mean(np.linalg.norm(origins - origins.mean(axis=0), axis=1))) or 0.1


def camera_focus(cameras: list) -> np.ndarray:
    """The point nearest to every camera's optical axis (least squares): where the cameras look."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for c in cameras:
        d = c.pose[:3, 2] / np.linalg.norm(c.pose[:3, 2])
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.pose[:3, 3]
    if len(cameras) < 2 or np.linalg.cond(A) > 1e8:
        return cameras[0].pose[:3, 3] + cameras[0].pose[:3, 2]
    return np.linalg.solve(A, b)


def camera_label(i: int, cam: ViewCamera) -> str:
    return f"{i}: {cam.name}{' (held out)' if cam.held_out else ''}"
