"""The web viewer (psdr_cli/viewer/) in a real browser: Debian's chromium, headless, driven by
Selenium through the system chromedriver (scripts/ensure-chromium.sh installs both; nothing is
downloaded at run time). The screenshots are checked for the mesh's and the cameras' colours
against one of an empty page; the Pause box is clicked in the browser and the loop must stop
writing log rows, then go on."""
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO
from test_optimize import TINY, default_sigint, log_rows, write

viser = pytest.importorskip("viser", reason="the viewer's extra is not installed: pip install 'psdr[view]'")
webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed: pip install 'psdr[test]'")

from psdr_cli import api  # noqa: E402
from psdr_cli.run_folder.layout import RunFiles, lock_run  # noqa: E402
from psdr_cli.viewer import server as viewer_server  # noqa: E402
from psdr_cli.viewer.pictures import read_png  # noqa: E402
from psdr_cli.viewer.run_folder_view import open_view  # noqa: E402

pytestmark = pytest.mark.xdist_group("browser")  # one headless chromium at a time

BROWSER = shutil.which("chromium") or shutil.which("chromium-browser")
DRIVER = shutil.which("chromedriver")
SHOT_SIZE = (1000, 700)


@pytest.fixture(scope="module")
def browser():
    """A headless chromium (software WebGL), or a skip when it cannot be installed here."""
    if not (BROWSER and DRIVER):
        pytest.skip("no chromium/chromedriver: scripts/ensure-chromium.sh installs them (as root, with apt)")
    os.environ["SE_OFFLINE"] = "true"  # Selenium Manager must not download a browser
    from selenium.webdriver.chrome.service import Service
    opts = webdriver.ChromeOptions()
    opts.binary_location = BROWSER
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={SHOT_SIZE[0]},{SHOT_SIZE[1]}",
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"):
        opts.add_argument(arg)
    driver = webdriver.Chrome(options=opts, service=Service(DRIVER))
    yield driver
    driver.quit()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def screenshot(driver, url: str, path: Path, settle: float = 6.0) -> np.ndarray:
    """The page at ``url`` once its scene has had ``settle`` seconds to draw, as 8-bit RGB."""
    driver.get(url)
    time.sleep(settle)
    for button in driver.find_elements("xpath", "//div[contains(., 'Software WebGL')]/button"):
        try:
            button.click()  # the notice that WebGL runs in software (chromium without a GPU)
        except Exception:  # noqa: BLE001  (another element of the same notice)
            pass
    time.sleep(0.5)
    driver.save_screenshot(str(path))
    return read_png(path)


def scene_part(shot: np.ndarray) -> np.ndarray:
    """The middle of the 3D view: right of the page's notices (orange-edged) and its axes gizmo
    (blue and green), left of the GUI panel (its loss curve is orange)."""
    return shot[:-80, 320: int(shot.shape[1] * 0.64)].astype(np.int32)


def mesh_pixels(shot: np.ndarray) -> int:
    """Pixels of the mesh's orange (viewer_server.MESH_COLOR, shaded)."""
    r, g, b = np.moveaxis(scene_part(shot), -1, 0)
    return int(np.sum((r > 90) & (r - b > 70) & (g - b > 20) & (r - g > 40)))


def frustum_pixels(shot: np.ndarray) -> int:
    """Pixels of the frustums' blue or the selected one's green."""
    r, g, b = np.moveaxis(scene_part(shot), -1, 0)
    return int(np.sum(((b - r > 100) & (b > 150)) | ((g - r > 100) & (g - b > 80))))


def tiny_run(tmp_path: Path, iterations: int = 4) -> Path:
    """A finished run of the test scene (a remesh-free sphere → bunny), its folder."""
    data = dict(TINY, optimize=dict(TINY["optimize"], remesh={"method": "instant", "initial": 150}))
    exp = api.load_experiment(write(tmp_path, data))
    api.optimize(exp, iterations=iterations)
    return exp.run_dir


def folder_state(root: Path) -> dict:
    return {p: p.stat().st_mtime_ns for p in sorted(root.rglob("*"))}


def test_view_draws_the_mesh_and_cameras_of_a_locked_run_and_writes_nothing(tmp_path, browser):
    """``psdr view RUN``: the last checkpoint's mesh and the cameras are drawn (their colours in
    the screenshot, none in an empty page's), while another process's lock is held on the run;
    clicking a camera's handle moves the page's viewpoint to it; nothing in the folder changes."""
    run = tiny_run(tmp_path)
    empty = viewer_server.ViewerServer(port=free_port())
    try:
        blank = screenshot(browser, empty.url, tmp_path / "empty.png", settle=3.0)
    finally:
        empty.close()
    before = folder_state(run)
    with lock_run(RunFiles(run)):  # as a running `psdr optimize` holds it
        server, refresh = open_view(run, port=free_port())
        try:
            shot = screenshot(browser, server.url, tmp_path / "view.png")
            refresh()
            clients = list(server.server.get_clients().values())
            assert clients, "the browser did not connect"
            server.snap_to(clients[0], 1)
            time.sleep(1.0)
            assert np.allclose(clients[0].camera.position, server.cameras[1].pose[:3, 3], atol=1e-3)
            assert server.selected == 1
        finally:
            server.close()
    assert folder_state(run) == before
    print(f"mesh pixels {mesh_pixels(shot)} (empty page {mesh_pixels(blank)}), "
          f"frustum pixels {frustum_pixels(shot)} (empty page {frustum_pixels(blank)})")
    assert mesh_pixels(blank) < 20 and frustum_pixels(blank) < 20
    assert mesh_pixels(shot) > 300, "the mesh is not drawn"
    assert frustum_pixels(shot) > 100, "the cameras are not drawn"


def test_view_refuses_what_is_not_a_run_or_mesh(tmp_path, run_psdr):
    (tmp_path / "notes.txt").write_text("x")
    for path, words in ((tmp_path / "absent", "no such file"), (tmp_path, "not a `psdr optimize` run folder"),
                        (tmp_path / "notes.txt", "expected a run folder or a .ply/.obj mesh")):
        r = run_psdr("view", path, "--seconds", "0.1")
        assert r.returncode == 2 and words in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_optimize_view_pause_in_the_browser_holds_the_loop(tmp_path, browser):
    """``psdr optimize --view``: the live page draws the mesh and cameras while the run goes;
    ticking Pause in the browser stops the log between iterations, unticking it resumes; Ctrl-C
    then ends the run as without the viewer. With PSDR_VIEWER_SCREENSHOT=1 the screenshot is
    kept as docs/images/viewer.png."""
    data = dict(TINY, optimize=dict(TINY["optimize"], iterations=2000, checkpoint_every=5, remesh={"method": "instant", "initial": 150}))
    cfg = write(tmp_path, data)
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "psdr_cli", "optimize", str(cfg), "--view", "--port", str(port)],
                            env=dict(os.environ, PYTHONUNBUFFERED="1"), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, preexec_fn=default_sigint)
    run = tmp_path / "runs" / "tiny"
    try:
        deadline = time.time() + 120
        while not ((run / "log.csv").exists() and len(log_rows(run)) >= 6):
            assert proc.poll() is None, proc.communicate()[0]
            assert time.time() < deadline, "the run did not start in time"
            time.sleep(0.2)
        shot = screenshot(browser, f"http://127.0.0.1:{port}/", tmp_path / "live.png", settle=8.0)
        assert mesh_pixels(shot) > 300 and frustum_pixels(shot) > 100, (mesh_pixels(shot), frustum_pixels(shot))
        if os.environ.get("PSDR_VIEWER_SCREENSHOT"):
            (REPO / "docs" / "images").mkdir(exist_ok=True)
            shutil.copy(tmp_path / "live.png", REPO / "docs" / "images" / "viewer.png")
        pause = browser.find_element("xpath", "//label[normalize-space()='Pause']")
        pause.click()
        time.sleep(2.0)  # the iteration in flight ends
        held = len(log_rows(run))
        time.sleep(3.0)
        assert len(log_rows(run)) == held, "the loop went on while paused"
        pause.click()
        deadline = time.time() + 60
        while len(log_rows(run)) <= held:
            assert time.time() < deadline, "the loop did not resume"
            time.sleep(0.2)
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 130, out
    assert "Traceback" not in out, out


def test_a_taken_port_and_a_failing_page_are_one_warning_each_and_the_run_goes_on(tmp_path):
    """The viewer moves off a port in use with one warning; a page update that fails stops the
    viewer's updates with one warning; the run ends as without a viewer."""
    data = dict(TINY, optimize=dict(TINY["optimize"], remesh={"method": "instant", "initial": 150}))
    exp = api.load_experiment(write(tmp_path, data))
    warnings = []
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        viewer = api.live_viewer(port=port, warn=warnings.append, interval=0.0)

        def broken(*args):
            raise ConnectionResetError("the page went away")
        viewer.server.show_mesh = broken
        try:
            result = api.optimize(exp, iterations=4, observer=viewer)
        finally:
            viewer.close()
    assert result.iterations == 4 and result.final.is_file()
    assert viewer.server.port != port
    assert [w for w in warnings if "in use" in w] and len([w for w in warnings if "stopped updating" in w]) == 1, warnings


def test_the_live_page_renders_the_selected_view_and_measures_the_chamfer_distance(tmp_path):
    """While the run goes the selected view is rendered at the current shape (target | render |
    error beside each other) and, with a reference mesh in the run folder, the Chamfer-L1 of the
    current shape is plotted (snapshots the page had no time for are skipped): at the last
    iteration it is psdr evaluate's distance of final.ply; the live render's PSNR is plotted too."""
    from psdr_cli.commands import evaluate as ev
    from psdr_cli.viewer.live import CHAMFER_SAMPLES, LiveViewer
    data = dict(TINY, optimize=dict(TINY["optimize"], remesh={"method": "instant", "initial": 150}))
    exp = api.load_experiment(write(tmp_path, data))
    viewer = LiveViewer(port=free_port(), warn=print, interval=0.0, render_interval=0.0, chamfer_interval=0.0)
    try:
        api.optimize(exp, iterations=4, observer=viewer)
        deadline = time.monotonic() + 20
        while not (viewer.chamfers and viewer.chamfers[-1][0] == 3) and time.monotonic() < deadline:
            time.sleep(0.1)  # the viewer's thread shows the last snapshot
        view, strip, live_psnr = viewer.live
        assert view == 0 and strip.ndim == 3 and strip.shape[1] > 3 * strip.shape[0] - 1
        assert viewer.psnrs[-1] == (3, live_psnr) and 5 < live_psnr < 99
        assert np.isfinite(strip).all() and strip[:, : strip.shape[1] // 3].max() > 0  # the target's third
        assert "live" in viewer.server.strip.label
        iterations, values = zip(*viewer.chamfers)
        assert iterations[-1] == 3 and list(iterations) == sorted(iterations) and all(np.isfinite(values))
        final = ev.distance(ev.load(exp.run_dir / "final.ply"), ev.load(exp.run_dir / "reference.ply"),
                            CHAMFER_SAMPLES).chamfer_l1
        assert values[-1] == pytest.approx(final, rel=1e-3)
    finally:
        viewer.close()


def test_the_live_page_of_a_capture_shows_held_out_cameras_and_the_refined_poses(tmp_path):
    """A camera dataset with pose refinement: the held-out cameras are drawn (held_out, their
    photographs as pictures) beside the training cameras, which are drawn at their refined poses
    (moved from the dataset's by the run's corrections, as cameras.json has them)."""
    import json
    from test_camera_refinement import dataset_experiment
    from psdr_cli.viewer.live import LiveViewer
    exp = api.load_experiment(dataset_experiment(tmp_path, cameras={"start": 0, "warmup": 0}))
    viewer = LiveViewer(port=free_port(), warn=print, interval=0.0, render_interval=1e9, chamfer_interval=1e9)
    try:
        api.optimize(exp, iterations=6, observer=viewer)
        deadline = time.monotonic() + 20
        while not (viewer.server.cameras and "6/6" in viewer.server.status.content) and time.monotonic() < deadline:
            time.sleep(0.1)  # the viewer's thread shows the last snapshot
        drawn = viewer.server.cameras
        refined = json.loads((exp.run_dir / "cameras.json").read_text())["views"]
        train = [c for c in drawn if not c.held_out]
        assert len(train) == len(refined) and any(c.held_out and c.image is not None for c in drawn)
        for cam, view in zip(train, refined):
            np.testing.assert_allclose(cam.pose, view["cam_to_world"], atol=1e-6)
        given = [c.pose for c in viewer.run.cameras if not c.held_out]
        assert max(float(np.abs(a.pose - b).max()) for a, b in zip(train, given)) > 1e-6  # they moved
    finally:
        viewer.close()


def test_a_viewer_that_fails_on_the_loop_thread_stops_with_one_warning_and_the_run_goes_on(tmp_path, monkeypatch):
    """A live render that fails (here: out of memory) stops the viewer with one warning; the run
    finishes as without a viewer."""
    from psdr_cli.viewer import live
    exp = api.load_experiment(write(tmp_path, dict(TINY, optimize=dict(TINY["optimize"],
                                                                        remesh={"method": "instant", "initial": 150}))))

    def out_of_memory(*args, **kwargs):
        raise RuntimeError("jit_malloc(): out of memory")
    monkeypatch.setattr(live, "render_view", out_of_memory)
    warnings = []
    viewer = live.LiveViewer(port=free_port(), warn=warnings.append, interval=0.0, render_interval=0.0)
    try:
        result = api.optimize(exp, iterations=4, observer=viewer)
    finally:
        viewer.close()
    assert result.iterations == 4 and result.final.is_file()
    assert len([w for w in warnings if w.startswith("viewer: stopped")]) == 1 and "out of memory" in warnings[0], warnings
