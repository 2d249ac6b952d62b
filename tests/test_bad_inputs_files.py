"""Files psdr writes and reads back, and sizes and names it must bound: a write that fails (a full
disk) leaves nothing under the final name and fails the command; a cached target that cannot be
read is rendered again; output paths that are not regular files are refused before any work;
sizes from XML films, textures and command-line options are bounded; leftovers that ended in
``internal error`` (a NUL in a name, a 400-digit number, stray checkpoint names, evaluate's
unnamed meshes) are one line naming the file and key.

Everything runs in-process (``psdr_cli.cli.run``) to keep the module fast."""
import copy
import importlib
import os
import re
import shutil
import stat
import struct
import zlib
from pathlib import Path

import mitsuba as mi
import numpy as np
import OpenEXR
import pytest
import yaml

from conftest import experiment
from psdr_cli import api, cli
from psdr_cli.errors import PsdrError
from psdr_cli.run_folder.checkpoints import run_checkpoints
from psdr_cli.run_folder.layout import RunFiles
from psdr_cli.scene import meshes
from psdr_cli.support import fileio
from psdr_cli.target_sources import rendered_mesh as targets
from test_faults import SMALL, assert_one_line_error, write_small
from test_faults import psdr as psdr_with_bars
from test_mitsuba_scene import write_twins

ENOSPC = "No space left on device"
#: A progress bar's line ("render ━━━━ 1/1 0:00:00"), printed once the work has begun.
BAR = re.compile(r"^[\w -]+ [━╸╺ ]*\d+/\d+ ")


def psdr(capsys, *args):
    """(exit code, stdout, stderr lines other than progress bars) of ``psdr ARGS`` in-process."""
    code, out, err = psdr_with_bars(capsys, *args)
    return code, out, [ln for ln in err if not BAR.match(ln)]


def module(name):
    """A module of psdr_cli (``psdr_cli.render`` the attribute is the API function)."""
    return importlib.import_module(f"psdr_cli.{name}")


# --------------------------------------------------------------------------------------------
# A full disk, simulated: the image libraries either raise (OpenEXR, Mitsuba on a big write) or
# return as if all went well, leaving an empty or cut file behind (Mitsuba's PNG writer when the
# disk fills up while the file is being closed).
# --------------------------------------------------------------------------------------------
REAL_EXR_FILE, REAL_BITMAP = OpenEXR.File, mi.Bitmap


def damage(path, how):
    """What a full disk does to a file being written: nothing ('raise': the writer reports it),
    an empty file or one cut in half (the writer returns as if all went well)."""
    if how == "raise":
        os.truncate(path, 0)
        raise RuntimeError(f'Failed to write pixel data to image file "{path}". {ENOSPC}.')
    os.truncate(path, 0 if how == "empty" else os.path.getsize(path) // 2)


def full_disk(monkeypatch, how, fmt, after=0):
    """Make the EXR or PNG writer fail like a full disk (``how``), from the ``after``-th write on."""
    count = [0]

    def failing(write_real):
        def write(path):
            write_real(path)
            count[0] += 1
            if count[0] > after:
                damage(path, how)
        return write

    if fmt == "exr":
        def exr_file(*args, **kwargs):
            f = REAL_EXR_FILE(*args, **kwargs)
            if len(args) >= 2:  # File(header, channels): a file to be written
                return type("Writer", (), {"__enter__": lambda s: s, "__exit__": lambda s, *e: False,
                                           "write": staticmethod(failing(f.write))})()
            return f
        monkeypatch.setattr(fileio.OpenEXR, "File", exr_file)
    else:
        def bitmap(*args, **kwargs):
            b = REAL_BITMAP(*args, **kwargs)
            if args and isinstance(args[0], np.ndarray):  # Bitmap(array): an image to be written
                return type("Writer", (), {"write": staticmethod(failing(b.write))})()
            return b
        bitmap.PixelFormat = REAL_BITMAP.PixelFormat
        monkeypatch.setattr(fileio.mi, "Bitmap", bitmap)


WRITES = [(how, fmt) for fmt in ("exr", "png") for how in ("raise", "empty", "half")]


@pytest.mark.parametrize("how,fmt", WRITES, ids=[f"{fmt}-{how}" for how, fmt in WRITES])
def test_a_failed_image_write_leaves_nothing(tmp_path, monkeypatch, how, fmt):
    full_disk(monkeypatch, how, fmt)
    target = tmp_path / f"image.{fmt}"
    image = np.random.default_rng(0).random((16, 24, 3))
    write = fileio.write_rgb_exr if fmt == "exr" else fileio.write_preview
    with pytest.raises(PsdrError, match=f"^{target}: cannot write"):
        write(target, image)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("how,fmt", [("empty", "png"), ("raise", "exr")], ids=["png-empty", "exr-raise"])
def test_render_on_a_full_disk_fails_and_writes_nothing(tmp_path, write_cfg, capsys, monkeypatch, how, fmt):
    monkeypatch.chdir(tmp_path)
    cfg = write_cfg(experiment(estimator={"spp": 1}))
    full_disk(monkeypatch, how, fmt)
    code, out, err = psdr(capsys, "render", cfg)
    assert_one_line_error(code, out, err, f"view_000.{fmt}: cannot write")
    assert "psdr render" not in out                      # no summary of files that do not exist
    left = [p for p in (tmp_path / "out").rglob("*") if p.is_file()]
    assert all(p.suffix == ".exr" and p.stat().st_size > 0 for p in left), left


def test_optimize_on_a_full_disk_leaves_no_empty_target_and_the_next_run_works(tmp_path, capsys, monkeypatch):
    """The second target (view_001.exr) hits the full disk: the command fails naming it, no
    target is left empty under its final name, and the next run (disk freed) renders it."""
    cfg = write_small(tmp_path)
    with monkeypatch.context() as m:
        full_disk(m, "empty", "exr", after=1)
        code, out, err = psdr(capsys, "optimize", cfg, "--iterations", "1")
    assert_one_line_error(code, out, err, "view_001.exr: cannot write")
    targets = RunFiles(tmp_path / "runs" / "small").targets
    assert all(p.stat().st_size > 0 for p in targets.glob("*.exr"))
    assert not (targets / "view_001.exr").exists()
    code, out, err = psdr(capsys, "optimize", cfg, "--iterations", "1")
    assert code == 0, err
    assert all(fileio.read_exr(p) for p in sorted(targets.glob("view_*.exr")))


def cut(path, how):
    if how == "empty":
        path.write_bytes(b"")
    elif how == "half":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif how in ("nan", "size"):
        rewrite_target(path, how)
    else:
        path.write_bytes(b"\x76\x2f\x31\x01 garbage" * 10)


def rewrite_target(path, how):
    """The cached target rewritten whole with its own header (its key still matches): one NaN
    pixel, or one row fewer than the film."""
    with OpenEXR.File(str(path)) as f:
        header = {k: v for k, v in f.header().items() if k.startswith("psdr.")}
        rgb = np.array(f.channels()["RGB"].pixels)
    if how == "nan":
        rgb[3, 4, 1] = np.nan
    else:
        rgb = np.ascontiguousarray(rgb[:-1])
    OpenEXR.File(header, {"RGB": rgb}).write(str(path))


ONE_ITERATION = dict(SMALL, optimize=dict(SMALL["optimize"], iterations=1, checkpoint_every=1))


@pytest.fixture(scope="module")
def one_iteration_run(tmp_path_factory):
    """A finished one-iteration run (copied by each test that changes it)."""
    folder = tmp_path_factory.mktemp("one")
    assert cli.run(["optimize", str(write_small(folder, ONE_ITERATION))]) == 0
    return folder


@pytest.mark.parametrize("how,resume", [("empty", True), ("half", True), ("garbage", False), ("nan", True),
                                        ("size", False)],
                         ids=["empty-resume", "half-resume", "garbage-fresh", "nan-resume", "size-fresh"])
def test_a_damaged_cached_target_is_rendered_again(one_iteration_run, tmp_path, capsys, how, resume):
    """A cached target that cannot be read (an earlier full disk, a copy cut short), or that
    reads back with the right key but a NaN pixel or the wrong size, is rendered again, with or
    without --resume; it is never trusted, never an internal error."""
    shutil.copytree(one_iteration_run, tmp_path / "copy")
    cfg = write_small(tmp_path / "copy", ONE_ITERATION)
    target = RunFiles(tmp_path / "copy" / "runs" / "small").targets / "view_000.exr"
    good = fileio.read_rgb_exr(target)
    cut(target, how)
    if resume:
        code, out, err = psdr(capsys, "optimize", cfg, "--resume", "--iterations", "2")
    else:  # the fresh run's folder is seeded with the old run's (damaged) targets
        code, out, err = psdr(capsys, "optimize", cfg)
    assert code == 0, err
    assert np.array_equal(fileio.read_rgb_exr(target), good)


# --------------------------------------------------------------------------------------------
# Output paths that are not regular files: refused in one line, before any work
# --------------------------------------------------------------------------------------------
def not_a_file(path: Path, kind: str):
    if kind == "folder":
        path.mkdir()
    elif kind == "fifo":
        os.mkfifo(path)
    else:  # a link to a device: the file must not be replaced, the device not written
        path.symlink_to("/dev/null")


def still_there(path: Path, kind: str) -> bool:
    mode = os.stat(path).st_mode
    return {"folder": stat.S_ISDIR, "fifo": stat.S_ISFIFO, "device": stat.S_ISCHR}[kind](mode)


KINDS = ["folder", "fifo", "device"]


@pytest.fixture(scope="module")
def sphere_ply(tmp_path_factory):
    folder = tmp_path_factory.mktemp("meshes")
    meshes.write_ply(folder / "a.ply", *meshes.sphere(1.0, 1))
    return folder / "a.ply"


@pytest.mark.parametrize("kind", KINDS)
def test_evaluate_json_that_is_not_a_file(tmp_path, capsys, sphere_ply, kind, monkeypatch):
    out_file = tmp_path / "out.json"
    not_a_file(out_file, kind)
    calls = []
    monkeypatch.setattr(module("commands.evaluate"), "distance", lambda *a, **k: calls.append(a))
    code, out, err = psdr(capsys, "evaluate", sphere_ply, "--reference", sphere_ply, "--samples", "100",
                          "--json", out_file)
    assert_one_line_error(code, out, err, f"{out_file}: --json: not a regular file")
    assert calls == [], "refused before any work"
    assert still_there(out_file, kind)


def test_devices_are_never_replaced(tmp_path):
    """atomic_path itself refuses a target that exists and is not a regular file."""
    for kind in KINDS:
        path = tmp_path / f"x_{kind}.json"
        not_a_file(path, kind)
        with pytest.raises(PsdrError, match="not a regular file"):
            fileio.write_json(path, {"a": 1})
        assert still_there(path, kind)
    assert fileio.temporaries(tmp_path) == []


def test_table2_out_that_is_a_folder(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cfg = write_small(tmp_path)
    (tmp_path / "t2.md").mkdir()
    code, out, err = psdr(capsys, "table2", cfg, "--out", tmp_path / "t2.md")
    assert_one_line_error(code, out, err, "t2.md: --out: not a regular file (a folder)")


def test_render_output_file_that_is_a_folder_is_refused_before_rendering(tmp_path, write_cfg, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cfg = write_cfg(experiment(estimator={"spp": 1}))
    blocked = tmp_path / "out" / "t" / "render" / "view_000.png"
    blocked.mkdir(parents=True)
    monkeypatch.setattr(module("rendering.render"), "render_view", lambda *a, **k: pytest.fail("rendered"))
    code, out, err = psdr(capsys, "render", cfg)
    assert_one_line_error(code, out, err, f"{blocked}: not a regular file (a folder)")
    assert blocked.is_dir() and not (blocked.parent / "view_000.exr").exists()


@pytest.mark.parametrize("name,kind", [("log.csv", "fifo"), ("final.ply", "folder"), ("state.npz", "device")])
def test_optimize_refuses_run_files_that_are_not_files_before_the_work(tmp_path, capsys, monkeypatch, name, kind):
    """A run folder whose log is a FIFO (reading it blocked --resume for ever), or whose final
    mesh or state is a folder or a device, is refused in one line before any iteration (the
    final mesh was refused only after the whole run)."""
    monkeypatch.chdir(tmp_path)
    cfg = write_small(tmp_path, ONE_ITERATION)
    run = tmp_path / "runs" / "small"
    run.mkdir(parents=True)
    not_a_file(run / name, kind)
    monkeypatch.setattr(module("commands.optimize"), "iterate", lambda *a, **k: pytest.fail("iterated"))
    code, out, err = psdr(capsys, "optimize", cfg, "--resume")
    assert_one_line_error(code, out, err, f"{run / name}: not a regular file")
    assert still_there(run / name, kind)


def test_grad_output_that_is_a_folder_is_refused_before_the_work(tmp_path, write_cfg, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cfg = write_cfg(experiment(estimator={"spp": 1}, parameter={"kind": "translate", "object": "ball",
                                                                "axis": [1, 0, 0]}))
    blocked = tmp_path / "out" / "t" / "grad" / "view_000.exr"
    blocked.mkdir(parents=True)
    monkeypatch.setattr(module("commands.gradient"), "forward_gradient", lambda *a, **k: pytest.fail("estimated"))
    code, out, err = psdr(capsys, "grad", cfg)
    assert_one_line_error(code, out, err, f"{blocked}: not a regular file (a folder)")


# --------------------------------------------------------------------------------------------
# Sizes on the newer paths
# --------------------------------------------------------------------------------------------
def png_header(path: Path, width: int, height: int):
    """A PNG that claims width × height pixels (one tiny, truncated data chunk): its header is
    all a size check may read."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64))
                     + chunk(b"IEND", b""))


def xml_experiment(tmp, res=None, film=None):
    xml_cfg, _ = write_twins(tmp)
    d = yaml.safe_load(xml_cfg.read_text())
    if res is not None:
        d["scene"]["params"]["res"] = res
    if film is not None:
        d["scene"]["film"] = film
    xml_cfg.write_text(yaml.safe_dump(d, sort_keys=False))
    return xml_cfg


def huge_texture(tmp, suffix=".png"):
    png_header(tmp / "huge.png", 20000, 20000)
    d = experiment(estimator={"spp": 1})
    d["scene"]["objects"][1]["bsdf"] = {"type": "diffuse", "reflectance": {"type": "bitmap", "file": "huge.png"}}
    return d


def huge_envmap(tmp):
    png_header(tmp / "sky.png", 30000, 15000)
    d = experiment(estimator={"spp": 1})
    d["scene"]["emitters"].append({"type": "envmap", "file": "sky.png"})
    return d


SIZE_CASES = [
    ("xml_film_0", lambda t: xml_experiment(t, res=0), ["render"], "scene.xml: sensor 0: film 24×0"),
    ("xml_film_60000", lambda t: xml_experiment(t, res=60000), ["render"], "scene.xml: sensor 0: film 24×60000"),
    ("xml_yaml_film_60000", lambda t: xml_experiment(t, film={"width": 60000, "height": 16}), ["render"],
     "scene.film.width: expected an integer <= 8192"),
    ("texture_20000", huge_texture, ["render"],
     "scene.objects[1].bsdf.reflectance.file: texture huge.png is 20000×20000 pixels"),
    ("envmap_30000", huge_envmap, ["render"], "scene.emitters[1].file: environment map sky.png is 30000×15000 pixels"),
    ("iterations_23_digits", lambda t: write_small(t), ["optimize", "--iterations", "1" * 23],
     "--iterations: expected an integer in [1, 1000000]"),
    ("iterations_yaml_1e23", lambda t: write_small(t, dict(SMALL, optimize=dict(SMALL["optimize"], iterations=10 ** 23))),
     ["optimize"], "optimize.iterations: expected an integer <= 1000000"),
    ("iterations_zero", lambda t: write_small(t), ["optimize", "--iterations", "0"],
     "--iterations: expected an integer in [1, 1000000], got 0"),
]


@pytest.mark.parametrize("make,args,expected", [c[1:] for c in SIZE_CASES], ids=[c[0] for c in SIZE_CASES])
def test_sizes_are_bounded(tmp_path, write_cfg, capsys, monkeypatch, make, args, expected):
    monkeypatch.chdir(tmp_path)
    made = make(tmp_path)
    cfg = made if isinstance(made, Path) else write_cfg(made)
    code, out, err = psdr(capsys, args[0], cfg, *args[1:])
    assert_one_line_error(code, out, err, expected)
    assert not [p for folder in (tmp_path / "out", tmp_path / "runs") for p in folder.rglob("*") if p.is_file()]


@pytest.mark.parametrize("samples", ["0", "99", "10000001", "1" * 23])
def test_evaluate_samples_are_bounded(capsys, sphere_ply, samples):
    code, out, err = psdr(capsys, "evaluate", sphere_ply, "--reference", sphere_ply, "--samples", samples)
    assert_one_line_error(code, out, err, f"--samples: expected an integer in [100, 10000000], got {samples}")


# --------------------------------------------------------------------------------------------
# Leftovers that ended in `internal error`
# --------------------------------------------------------------------------------------------
def fov_digits(d):
    d["scene"]["cameras"][0]["fov"] = 10 ** 400
    return d


def nul_in(key):
    def make(d):
        if key == "name":
            d["name"] = "a\0b"
        elif key == "output":
            d["output"] = "o\0ut"
        else:
            d["scene"]["objects"][0]["mesh"] = {"file": "ball\0.ply"}
        return d
    return make


LEFTOVER_CASES = [
    ("name_nul", nul_in("name"), "name: expected a string without NUL characters"),
    ("output_nul", nul_in("output"), "output: expected a string without NUL characters"),
    ("mesh_file_nul", nul_in("mesh"), "scene.objects[0].mesh.file: expected a string without NUL characters"),
    ("fov_400_digits", fov_digits, "scene.cameras[0].fov: expected a number representable in float32"),
    ("translate_400_digits", lambda d: (d["scene"]["objects"][0].update(transform={"translate": [0, 10 ** 400, 0]}), d)[1],
     "scene.objects[0].transform.translate: expected 3 finite numbers"),
]


@pytest.mark.parametrize("make,expected", [c[1:] for c in LEFTOVER_CASES], ids=[c[0] for c in LEFTOVER_CASES])
def test_leftover_inputs_are_one_line(tmp_path, capsys, monkeypatch, make, expected):
    monkeypatch.chdir(tmp_path)
    cfg = tmp_path / "exp.yaml"
    cfg.write_text(yaml.safe_dump(make(copy.deepcopy(experiment())), sort_keys=False, allow_unicode=True))
    code, out, err = psdr(capsys, "render", cfg)
    assert_one_line_error(code, out, err, expected)
    assert err[0].startswith(f"error: {cfg}: ")
    assert len(err[0]) < 400, "one readable line (a 400-digit number is not repeated)"


def test_stray_checkpoint_names_are_ignored(tmp_path):
    checkpoints = RunFiles(tmp_path).checkpoints
    checkpoints.mkdir()
    for name in ("iter_0000.ply", "iter_0010.ply", "iter_abc.ply", "iter_.ply", "iter_0010 (copy).ply",
                 "iter_0005.ply.bak"):
        (checkpoints / name).write_text("ply\n")
    assert [(i, p.name) for i, p in run_checkpoints(tmp_path)] == [(0, "iter_0000.ply"), (10, "iter_0010.ply")]
    for p in checkpoints.glob("iter_00*.ply"):
        p.unlink()
    with pytest.raises(PsdrError, match="no checkpoints"):
        run_checkpoints(tmp_path)


EVAL_MESHES = {
    "nan_vertex": "v 0 0 0\nv 1 0 0\nv 0 nan 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n",
    "degenerate": "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n",
}


@pytest.mark.parametrize("role", ["mesh", "reference"])
@pytest.mark.parametrize("name", list(EVAL_MESHES))
def test_evaluate_names_the_bad_mesh(tmp_path, capsys, sphere_ply, name, role):
    bad = tmp_path / f"{name}.obj"
    bad.write_text(EVAL_MESHES[name])
    mesh, ref = (bad, sphere_ply) if role == "mesh" else (sphere_ply, bad)
    code, out, err = psdr(capsys, "evaluate", mesh, "--reference", ref, "--samples", "100")
    assert_one_line_error(code, out, err, f"{bad}: ")


# --------------------------------------------------------------------------------------------
# Cached targets are keyed on every file the scene reads
# --------------------------------------------------------------------------------------------
EXTRA_XML = """<scene version="3.0.0">
  <emitter type="envmap"><string name="filename" value="sky.exr"/><float name="scale" value="0.2"/></emitter>
  <shape type="rectangle" id="panel">
    <transform name="to_world"><translate value="0, 2, 1"/></transform>
    <bsdf type="diffuse"><texture type="bitmap" name="reflectance"><string name="filename" value="$tex"/></texture>
    </bsdf></shape>
</scene>
"""


def small_png(path, value):
    mi.Bitmap(np.full((4, 4, 3), value, np.uint8), pixel_format=mi.Bitmap.PixelFormat.RGB).write(str(path))


def xml_with_include(tmp):
    """The twins' XML scene with an <include>d file naming a texture (through a $param) and an
    environment map."""
    xml_cfg, _ = write_twins(tmp, extra_xml='<include filename="extra.xml"/>')
    (tmp / "extra.xml").write_text(EXTRA_XML)
    small_png(tmp / "checker.png", 128)
    fileio.write_rgb_exr(tmp / "sky.exr", np.full((8, 16, 3), 0.5))
    d = yaml.safe_load(xml_cfg.read_text())
    d["scene"]["params"]["tex"] = "checker.png"
    d["optimize"] = {"object": "ball"}
    xml_cfg.write_text(yaml.safe_dump(d, sort_keys=False))
    return xml_cfg


def yaml_with_files(tmp):
    """A YAML scene whose floor is a mesh file and whose sky an environment map."""
    V, F = meshes.plane((4.0, 4.0))[:2]
    meshes.write_ply(tmp / "floor.ply", V, F)
    fileio.write_rgb_exr(tmp / "sky.exr", np.full((8, 16, 3), 0.5))
    d = experiment()
    d["scene"]["objects"][1]["mesh"] = {"file": "floor.ply"}
    d["scene"]["emitters"].append({"type": "envmap", "file": "sky.exr"})
    d["optimize"] = {"object": "ball"}
    path = tmp / "exp.yaml"
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path


def retexture(tmp):
    small_png(tmp / "checker.png", 40)


def recolour_include(tmp):
    (tmp / "extra.xml").write_text(EXTRA_XML.replace('<float name="scale" value="0.2"/>',
                                                     '<float name="scale" value="0.3"/>'))


def relight(tmp):
    fileio.write_rgb_exr(tmp / "sky.exr", np.full((8, 16, 3), 0.7))


def move_floor(tmp):
    V, F = meshes.read_mesh_file(tmp / "floor.ply")
    meshes.write_ply(tmp / "floor.ply", V + [0, 0, -0.1], F)


KEY_CASES = [
    ("xml_included_file", xml_with_include, recolour_include),
    ("xml_texture", xml_with_include, retexture),
    ("xml_envmap", xml_with_include, relight),
    ("yaml_mesh_file", yaml_with_files, move_floor),
    ("yaml_envmap", yaml_with_files, relight),
]


@pytest.mark.parametrize("make,change", [c[1:] for c in KEY_CASES], ids=[c[0] for c in KEY_CASES])
def test_target_key_covers_every_file_the_scene_reads(tmp_path, make, change):
    cfg = make(tmp_path)
    reference = meshes.sphere(0.4, 1)

    def key():
        return targets.target_key(api.load_experiment(cfg, warn=lambda m: None), reference, 4)

    before = key()
    assert key() == before, "the same files give the same key"
    change(tmp_path)
    after = key()
    assert after != before, "an edited file the scene reads must make new targets"


def test_huge_texture_named_by_an_included_xml(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cfg = xml_with_include(tmp_path)
    png_header(tmp_path / "huge.png", 20000, 20000)
    d = yaml.safe_load(cfg.read_text())
    d["scene"]["params"]["tex"] = "huge.png"
    cfg.write_text(yaml.safe_dump(d, sort_keys=False))
    code, out, err = psdr(capsys, "render", cfg)
    assert_one_line_error(code, out, err, "extra.xml: image huge.png is 20000×20000 pixels")


def image_headers(folder: Path, width: int, height: int) -> dict:
    """Files of every format Mitsuba decodes that claim width × height pixels in their headers
    (the pixel data cut short: only a header may be read)."""
    bmp = struct.pack("<2sIHHIIiiHHIIiiII", b"BM", 54, 0, 0, 54, 40, width, height, 1, 24, 0, 0, 0, 0, 0, 0)
    tga = struct.pack("<BBBHHBHHHHBB", 0, 0, 2, 0, 0, 0, 0, 0, width, height, 24, 0)
    files = {"a.hdr": b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y %d +X %d\n" % (height, width) + b"\0" * 64,
             "a.pfm": b"PF\n%d %d\n-1.0\n" % (width, height) + b"\0" * 64,
             "a.ppm": b"P6\n%d %d\n255\n" % (width, height) + b"\0" * 64,
             "a.bmp": bmp + b"\0" * 64, "a.tga": tga + b"\0" * 64}
    paths = {}
    for name, data in files.items():
        paths[name] = folder / name
        paths[name].write_bytes(data)
    return paths


def test_image_sizes_of_every_format_mitsuba_reads_come_from_their_headers(tmp_path):
    """A 20000 × 20000 image in HDR, PFM, PPM, BMP or TGA is refused from its header (before:
    only PNG, JPEG and EXR were; the others were decoded whole)."""
    for name, path in image_headers(tmp_path, 20000, 20000).items():
        assert fileio.image_size(path) == (20000, 20000), name
        assert "is 20000×20000 pixels" in fileio.image_too_large(path, 2 ** 27), name


@pytest.mark.parametrize("name", ["a.hdr", "a.pfm", "a.bmp"])
def test_huge_texture_of_another_format_named_by_an_included_xml(tmp_path, capsys, monkeypatch, name):
    monkeypatch.chdir(tmp_path)
    cfg = xml_with_include(tmp_path)
    image_headers(tmp_path, 20000, 20000)
    d = yaml.safe_load(cfg.read_text())
    d["scene"]["params"]["tex"] = name
    cfg.write_text(yaml.safe_dump(d, sort_keys=False))
    code, out, err = psdr(capsys, "render", cfg)
    assert_one_line_error(code, out, err, f"extra.xml: image {name} is 20000×20000 pixels")
