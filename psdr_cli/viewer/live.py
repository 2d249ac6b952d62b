"""The live viewer of ``psdr optimize --view``: the loop's observer. Each call from the loop is
cheap and never waits on the page: at most every ``interval`` seconds it copies the current
vertices (and the refined camera poses) and leaves them in a one-slot mailbox that a background
thread takes to the page; it blocks the loop only while the page's Pause box is ticked (between
iterations: the saved state is that of the last finished iteration). Reads the run folder's
previews, environment map and texture as the run writes them; writes nothing."""
from __future__ import annotations

import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import numpy as np

from ..errors import PsdrWarning
from ..scoring.held_out import psnr
from ..scoring.mesh_distance import distance
from ..experiment.dataset_frame import dataset_frames
from ..optimisation.camera_refinement import OPENCV_FLIP
from ..optimisation.start_state import dataset_coordinates
from ..rendering.render import render_view
from ..run_folder.refined_cameras import refined_poses
from ..run_folder.checkpoints import strip
from ..run_folder.layout import RunFiles
from ..scene.meshes import read_mesh_file
from .frustums import ViewCamera, config_camera, pinhole_camera
from .pictures import read_png, rgb8, thumbnail
from .run_folder_view import newest_preview, run_pictures
from .server import ViewerServer


#: Samples per pixel of the selected view's live render.
RENDER_SPP = 4

#: Points sampled on each mesh for the live Chamfer-L1 (:func:`psdr_cli.scoring.mesh_distance.distance`).
CHAMFER_SAMPLES = 20_000


@dataclass
class Snapshot:
    """What the loop hands over: the shape (scene coordinates), the refined cameras' transforms
    (Mitsuba axes; None without pose refinement), the iteration count and optimisation seconds,
    and the selected view's (index, target | render | |error| strip in linear RGB, PSNR of the
    render against its target) when one was rendered for it."""
    V: np.ndarray
    F: np.ndarray
    camera_matrices: np.ndarray | None
    done: int
    total: int
    seconds: float
    strip: tuple | None = None


@dataclass
class RunScene:
    """What does not change while one run goes: its experiment, folder, cameras as first drawn and
    the data to move the training cameras by their refinement."""
    exp: object
    files: RunFiles
    cameras: list
    frames: list | None        # a dataset's training frames (their poses), None for a scene's cameras
    initial: np.ndarray | None  # the cameras' transforms before refinement (Mitsuba axes)
    reference: tuple | None = None  # the run's reference mesh (V, F) when it has one


class LiveViewer:
    """The observer of :func:`psdr_cli.commands.optimize.optimize`: ``iteration(...)`` after each saved
    iteration. A viewer that cannot serve, or whose page fails, prints one warning and the run
    goes on without it."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, warn=print, interval: float = 1.0,
                 render_interval: float = 5.0, chamfer_interval: float = 10.0):
        """Serve on ``host``:``port``; hand the shape over at most every ``interval`` seconds,
        render the selected view at most every ``render_interval`` seconds (on the loop's thread)
        and measure the Chamfer-L1 to a reference mesh at most every ``chamfer_interval`` seconds
        (on the viewer's thread)."""
        self.warn, self.interval = warn, interval
        self.render_interval, self.chamfer_interval = render_interval, chamfer_interval
        self.last_render = self.last_chamfer = -np.inf
        self.chamfers: list = []
        self.psnrs: list = []  # (iteration, PSNR of the live render of the view selected then)
        self.resume = threading.Event()
        self.resume.set()
        self.wake = threading.Condition()
        self.pending: Snapshot | None = None
        self.run: RunScene | None = None
        self.losses: list = []
        self.last_push = -np.inf
        self.started = None  # (monotonic time, iterations done) when this viewer first saw the run
        self.closed = False
        self.live = None  # (view, strip) of the last live render
        try:
            self.server = ViewerServer(host, port, "psdr optimize", warn)
        except Exception as exc:  # noqa: BLE001  (a host that cannot be bound, ...: the run goes on)
            warn(f"viewer: cannot serve on {host}:{port} ({exc}); the run goes on without it")
            self.server = None
            return
        self.pause_box = self.server.server.gui.add_checkbox("Pause", False, order=10,
                                                             hint="Hold the loop between iterations")
        self.pause_box.on_update(lambda _: self.set_paused(self.pause_box.value))
        self.server.on_view(lambda _: self.show_strip())
        self.thread = threading.Thread(target=self.push_forever, name="psdr-viewer", daemon=True)
        self.thread.start()

    @property
    def url(self) -> str | None:
        return self.server.url if self.server else None

    @property
    def paused(self) -> bool:
        return not self.resume.is_set()

    def set_paused(self, paused: bool):
        """Pause (the loop blocks after its current iteration) or resume the run."""
        if paused:
            self.resume.clear()
        else:
            self.resume.set()
        if self.server and self.pause_box.value != paused:
            self.pause_box.value = paused

    def iteration(self, exp, now, done: int, total: int, seconds: float, loss: float):
        """After iteration ``done - 1`` was saved (called on the loop's thread): the loss kept,
        a snapshot handed over when ``interval`` has passed (or the run ends), then held here
        while paused. Whatever fails in the viewer stops the viewer with one warning, never the
        run."""
        if self.server is None or self.closed:
            return
        try:
            self.hand_over(exp, now, done, total, seconds, loss)
        except Exception as exc:  # noqa: BLE001  (a render, a file, the page: the run goes on)
            self.warn(f"viewer: stopped ({type(exc).__name__}: {exc}); the run goes on")
            self.close()
            return
        while not self.resume.wait(0.2):
            pass

    def hand_over(self, exp, now, done: int, total: int, seconds: float, loss: float):
        """The loss kept and, when ``interval`` has passed (or the run ends, or it is paused), a
        snapshot (with the selected view's live render every ``render_interval``) handed to the
        viewer's thread."""
        if self.run is None or self.run.exp.run_dir != exp.run_dir:
            self.start_run(exp, now, done)
        self.losses.append((done - 1, loss))
        t = time.monotonic()
        if t - self.last_push >= self.interval or done == total or self.paused:
            self.last_push = t
            cams = now.problem.cameras
            strip = None
            if t - self.last_render >= self.render_interval or done == total:
                self.last_render = t
                strip = self.live_strip(now)
            snapshot = Snapshot(now.problem.vertices(), now.problem.F, cams.matrices() if cams else None,
                                done, total, seconds, strip)
            with self.wake:
                self.pending = snapshot
                self.wake.notify()

    def start_run(self, exp, now, done: int):
        """The cameras of a run the viewer has not seen yet (one-time, on the loop's thread)."""
        cams = now.problem.cameras
        files = RunFiles(exp.run_dir)
        reference = read_mesh_file(files.reference) if files.reference.exists() else None
        self.run = RunScene(exp, files, *run_cameras(exp, now.stage.images),
                            None if cams is None else np.array(cams.initial), reference)
        self.losses, self.chamfers, self.psnrs, self.started = [], [], [], (time.monotonic(), done)
        self.live = None

    def live_strip(self, now) -> tuple | None:
        """(view, target | render | |error|, PSNR of the render against the target) of the
        selected training view at the current shape: :data:`RENDER_SPP` samples per pixel at the
        stage's resolution (on the loop's thread, between iterations, as the checkpoints' previews
        are rendered)."""
        view = self.server.selected
        targets = now.stage.images
        if view >= len(targets):
            return None  # a held-out camera: no target in the loop
        with dr.suspend_grad():
            image = render_view(now.problem.scene, view, RENDER_SPP, seed=self.run.exp.seed)
        target = np.asarray(targets[view], np.float64).reshape(image.shape)
        image = np.asarray(image, np.float64)
        return view, strip(target, image, zoom=max(1, 192 // max(image.shape[:2]))), psnr(image, target)

    def push_forever(self):
        """The background thread: each snapshot handed over, shown on the page."""
        while True:
            with self.wake:
                while self.pending is None and not self.closed:
                    self.wake.wait()
                if self.closed:
                    return
                snapshot, self.pending = self.pending, None
            try:
                self.show(snapshot)
            except Exception as exc:  # noqa: BLE001  (the page failed: the run goes on without it)
                self.warn(f"viewer: stopped updating ({type(exc).__name__}: {exc}); the run goes on")
                return

    def show(self, s: Snapshot):
        """One snapshot on the page: mesh, cameras, losses, status, previews and pictures."""
        run, server = self.run, self.server
        server.show_mesh(dataset_coordinates(run.exp, s.V), s.F)
        server.show_cameras(moved_cameras(run, s.camera_matrices))
        iterations, losses = zip(*self.losses) if self.losses else ((), ())
        server.show_losses(iterations, losses)
        self.show_chamfer(s)
        server.show_status(self.status_line(s))
        if s.strip is not None:
            self.live = s.strip
            self.psnrs.append((s.done - 1, s.strip[2]))
            server.show_psnr(*zip(*self.psnrs))
        self.show_strip()
        for name, image in run_pictures(run.files).items():
            server.show_picture(name, image)

    def show_chamfer(self, s: Snapshot):
        """The Chamfer-L1 of the snapshot's shape to the run's reference mesh (when it has one), at
        most every ``chamfer_interval`` seconds, and its curve."""
        t = time.monotonic()
        if self.run.reference is None or (t - self.last_chamfer < self.chamfer_interval and s.done != s.total):
            return
        self.last_chamfer = t
        shape = (dataset_coordinates(self.run.exp, s.V), s.F)
        self.chamfers.append((s.done - 1, distance(shape, self.run.reference, CHAMFER_SAMPLES).chamfer_l1))
        self.server.show_chamfer(*zip(*self.chamfers))

    def show_strip(self):
        """The selected view's live strip when it was rendered last, else its newest preview strip
        from the run folder (or its target)."""
        if self.run is None:
            return
        view = self.server.selected
        if self.live is not None and self.live[0] == view:
            self.server.show_strip(rgb8(self.live[1]), f"view {view}, live: target | render | error")
            return
        path = newest_preview(self.run.files, view)
        strip = read_png(path) if path else None
        if strip is not None:
            self.server.show_strip(strip, f"view {view}, {path.name[:9]}: target | render | error")
            return
        cams = self.run.cameras
        self.server.show_strip(cams[view].image if view < len(cams) else None,
                               f"view {view}: target (no preview: not in optimize.preview_views)")

    def status_line(self, s: Snapshot) -> str:
        """Iteration, stage, speed and time left (markdown)."""
        cfg = self.run.exp.optimize
        stages = 1 + sum(1 for a in cfg.remesh.at if a > 0)
        stage = 1 + sum(1 for a in cfg.remesh.at if 0 < a <= s.done - 1)
        t0, done0 = self.started
        rate = (time.monotonic() - t0) / max(s.done - done0, 1)
        left = rate * (s.total - s.done)
        if cfg.seconds is not None:
            left = min(left, max(cfg.seconds - s.seconds, 0.0))
        state = " · **paused**" if self.paused else ""
        return (f"**{self.run.exp.name}** · iteration {s.done}/{s.total} · stage {stage}/{stages} · "
                f"{rate:.2f} s/iteration · about {left:.0f} s left{state}")

    def close(self):
        """Stop the background thread and the server."""
        self.closed = True
        self.resume.set()
        if self.server is None:
            return
        with self.wake:
            self.wake.notify()
        self.server.close()


def run_cameras(exp, targets: list) -> tuple:
    """(cameras, training frames or None) of a run: a dataset's training and held-out frames, or
    the scene's cameras, with the stage's targets as the training cameras' thumbnails."""
    pictures = [thumbnail(rgb8(t)) for t in targets]
    dataset = exp.optimize.target_dataset
    if dataset is None:
        cameras = [config_camera(f"camera {v}", cam, exp.scene.width, exp.scene.height,
                                 pictures[v] if v < len(pictures) else None)
                   for v, cam in enumerate(exp.scene.cameras)]
        return cameras, None
    with warnings.catch_warnings():  # the dataset's warnings were given when the run read it
        warnings.simplefilter("ignore", PsdrWarning)
        train = dataset_frames(dataset, "train")[1]
        try:
            held_out = dataset_frames(dataset, "test")[1]
        except Exception:  # noqa: BLE001  (a dataset without held-out views)
            held_out = []
    cameras = [pinhole_camera(f.name, f.cam_to_world, f.fy, f.width, f.height,
                              pictures[v] if v < len(pictures) else None) for v, f in enumerate(train)]
    cameras += [pinhole_camera(f.name, f.cam_to_world, f.fy, f.width, f.height, held_out_thumbnail(f.image), True)
                for f in held_out]
    return cameras, train


def held_out_thumbnail(image: Path):
    picture = read_png(image)
    return None if picture is None else thumbnail(picture)


def moved_cameras(run: RunScene, matrices) -> list:
    """The run's cameras with the training ones at their refined poses (``matrices``: Mitsuba
    axes, scene coordinates; None: as first drawn)."""
    if matrices is None:
        return run.cameras
    if run.frames is None:
        poses = [M @ OPENCV_FLIP for M in matrices]
    else:
        poses = refined_poses([f.cam_to_world for f in run.frames], run.initial, matrices,
                              run.exp.optimize.target_dataset.frame)
    moved = [ViewCamera(c.name, np.asarray(P), c.fov, c.aspect, c.image, c.held_out)
             for c, P in zip(run.cameras, poses)]
    return moved + run.cameras[len(moved):]
