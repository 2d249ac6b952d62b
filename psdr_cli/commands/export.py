"""``psdr export RUN_OR_MESH [--out DIR] [--texture IMAGE]``: a reconstruction as assets other tools
open: Wavefront OBJ + MTL + PNG and binary glTF 2.0 (.glb). Reads a run folder or a mesh file;
writes the export folder.

From a ``psdr optimize`` run folder: ``final.ply`` (already in the user's coordinates) with the
texture coordinates and the recovered albedo of the run's ``state.npz`` (``optimize.albedo``: a
texture, written as ``albedo.png``, or one colour); without a recovered albedo, the object's own
constant reflectance from the run's experiment (``optimize.json`` names it), else grey. With
``optimize.envmap_rotation``, the experiment's environment map is written rotated by the recovered
angle (``environment.exr``: used in place of the emitter's file, with the same ``rotate_deg`` and
``scale``, it lights the scene as the run's last iteration did); with ``optimize.envmap``, the
recovered map exp(x) is that file. From a mesh file (PLY/OBJ): the
mesh, grey, or with ``--texture`` an image looked up at the mesh's UVs.

Materials: MTL ``Kd`` (linear) or ``map_Kd``; glTF metallic-roughness with ``baseColorTexture``
(sRGB PNG) or ``baseColorFactor`` (linear), metallic 0, roughness 1, or the recovered
``optimize.material`` values (a principled roughness as it is, a rough conductor's or
dielectric's α as √α; the specular level only in ``export.json``). Recovered as textures
(``optimize.material.NAME.texture``), roughness and metallic become the glTF
``metallicRoughnessTexture`` (linear PNG: G roughness, B metallic, factors 1) and the MTL's PBR
maps ``map_Pr`` / ``map_Pm`` (linear grey PNGs); as values, the factors and ``Pr`` / ``Pm``.
UVs are Mitsuba's (v down the image) in the glTF file, as glTF has them, and flipped (v up) in
the OBJ, as OBJ has them.

Nothing is half-written: every file is written into a temporary folder next to the output
folder, which is renamed into place at the end (replacing a previous export there, recognised by
its ``export.json``; a folder holding anything else is refused).
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import mitsuba as mi
import numpy as np
import trimesh
from PIL import Image

from ..config.objects import BitmapConfig
from ..errors import ConfigError, PsdrError
from ..experiment.load import load_experiment
from ..optimisation.unknowns import registry
from ..optimisation.unknowns.asset import PBR_PNG, Asset
from ..run_folder.layout import RunFiles
from ..run_folder.state import State
from ..scene import meshes
from ..scene.build import read_bitmap
from ..support import fileio

#: Files of an export (export.json lists the ones written).
OBJ, MTL, PNG, GLB, ENV, RECORD = "mesh.obj", "mesh.mtl", "albedo.png", "mesh.glb", "environment.exr", "export.json"
MR_PNG = "metallic_roughness.png"  # glTF: G roughness, B metallic (linear); PBR_PNG: MTL map_Pr, map_Pm


@dataclass
class ExportResult:
    folder: Path
    files: list = field(default_factory=list)
    notes: list = field(default_factory=list)   # what was not exported, and why (one line each)


def export(source, out=None, texture=None, warn=print) -> ExportResult:
    """Export a run folder or a mesh file (module docstring) into ``out`` (default: the run's
    ``export/``, or ``<mesh>_export/`` next to a mesh file); returns what was written."""
    source = Path(source)
    if not source.exists():
        raise PsdrError(f"{source}: not found (expected a `psdr optimize` run folder or a .ply/.obj mesh)")
    if source.is_dir():
        if texture is not None:
            raise PsdrError(f"--texture: only for a mesh file (the run {source} has its own albedo)")
        asset = run_asset(source, warn)
        folder = Path(out) if out is not None else source / "export"
    else:
        asset = mesh_asset(source, texture)
        folder = Path(out) if out is not None else source.with_name(f"{source.stem}_export")
    check_asset(asset, source)
    files = write_folder(folder, asset)
    for note in asset.notes:
        warn(note)
    return ExportResult(folder, files, asset.notes)


# --------------------------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------------------------
def run_asset(folder: Path, warn) -> Asset:
    """The :class:`Asset` of a finished run folder."""
    files = RunFiles(folder)
    if not files.state.is_file():
        raise PsdrError(f"{folder}: not a `psdr optimize` run folder (no state.npz)")
    if not files.final.is_file():
        raise PsdrError(f"{folder}: the run is unfinished (no final.ply); finish it with `psdr optimize --resume`")
    state = State.load(files.state)
    V, F = read_mesh(files.final)[:2]
    if len(V) != len(state.V) or not np.array_equal(F, np.asarray(state.F, np.int64)):
        raise PsdrError(f"{folder}: final.ply is not the mesh of the saved state (the run was continued "
                        f"and is unfinished); finish it with `psdr optimize --resume`")
    asset = Asset(V, F, record={"source": str(folder), "iteration": state.iteration})
    exp = run_experiment(files, asset.notes, warn)
    for unknown in registry.UNKNOWNS:  # what each recovered (optimisation/unknowns: Unknown.export)
        unknown.export(asset, state, exp, files.state)
    return asset


def run_experiment(files: RunFiles, notes: list, warn):
    """The experiment of a run (``optimize.json`` names its file), or None with a note."""
    try:
        path = Path(json.loads(files.summary.read_text())["experiment"])
    except (OSError, ValueError, KeyError, TypeError):
        notes.append(f"{files.summary}: unreadable; the run's experiment (its object's colour, its environment) "
                     f"is not used")
        return None
    if not path.is_file():
        notes.append(f"{path}: the run's experiment file is gone; its object's colour and environment are not used")
        return None
    try:
        return load_experiment(path, warn)
    except PsdrError as exc:
        notes.append(f"the run's experiment cannot be read ({exc}); its object's colour and environment are not used")
        return None


def read_mesh(path: Path):
    """(V, F, UV or None) of a PLY/OBJ file as Mitsuba reads it, or one error line."""
    if path.suffix.lower() not in (".ply", ".obj"):
        raise PsdrError(f"{path}: unsupported mesh format '{path.suffix}' (expected .ply or .obj, or a run folder)")
    try:
        V, F, uv = meshes.read_mesh_file_uv(path)
    except Exception as exc:  # noqa: BLE001 - any parser failure is a bad file
        raise PsdrError(f"{path}: cannot read the mesh ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    if len(V) == 0 or len(F) == 0:
        raise PsdrError(f"{path}: the mesh is empty")
    return np.asarray(V, np.float64), np.asarray(F, np.int64), uv


def mesh_asset(path: Path, texture) -> Asset:
    """The :class:`Asset` of a mesh file, grey or with the ``texture`` image (linear texels)."""
    V, F, uv = read_mesh(path)
    asset = Asset(V, F, record={"source": str(path)})
    if texture is None:
        return asset
    texture = Path(texture)
    if uv is None:
        raise PsdrError(f"{path}: --texture: the mesh has no UV coordinates (an OBJ with 'vt' or a PLY with s, t)")
    if not texture.is_file():
        raise PsdrError(f"{texture}: --texture: not found")
    try:
        bitmap = read_bitmap(BitmapConfig(file=texture), "reflectance", str(texture), "--texture")
        texels = np.asarray(bitmap.convert(pixel_format=mi.Bitmap.PixelFormat.RGB,
                                           component_format=mi.Struct.Type.Float32, srgb_gamma=False), np.float64)
    except ConfigError as exc:
        raise PsdrError(str(exc)) from None
    asset.uv, asset.texture = uv, texels
    return asset


def check_asset(asset: Asset, source: Path):
    """Refuse what cannot be written faithfully: non-finite vertices, UVs or texels, UVs that do
    not match the vertices."""
    if not np.isfinite(asset.V).all():
        raise PsdrError(f"{source}: the mesh has NaN or infinite vertices")
    if asset.texture is not None:
        if asset.uv is None or len(asset.uv) != len(asset.V):
            raise PsdrError(f"{source}: a texture needs one UV per vertex")
        if not np.isfinite(asset.uv).all():
            raise PsdrError(f"{source}: the mesh has NaN or infinite UV coordinates")
        bad = int((~np.isfinite(asset.texture)).any(-1).sum())
        if bad:
            raise PsdrError(f"{source}: the texture has {bad} texels with NaN or infinite values")
    if asset.environment is not None and not np.isfinite(asset.environment).all():
        raise PsdrError(f"{source}: the exported environment has NaN or infinite values")


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------
def write_folder(folder: Path, asset: Asset) -> list:
    """Every file into a temporary folder next to ``folder``, then renamed onto it (a previous
    export there is replaced; a folder with other contents is refused). Returns the paths."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise PsdrError(f"{folder}: --out: not a folder")
    if folder.is_dir() and any(folder.iterdir()) and not (folder / RECORD).is_file():
        raise PsdrError(f"{folder}: --out: the folder holds files that are not a psdr export; give an empty "
                        f"or new folder")
    try:
        folder.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".tmp", dir=folder.parent))
    except OSError as exc:
        raise PsdrError(f"{folder}: cannot write the export folder ({fileio.describe_os_error(exc)})") from None
    try:
        names = write_files(tmp, asset)
        old = None
        if folder.exists():
            old = folder.with_name(f".{folder.name}.{os.getpid()}.old")
            folder.rename(old)
        tmp.rename(folder)
        fileio.flush_to_disk(folder.parent)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except OSError as exc:
        raise PsdrError(f"{folder}: cannot write the export ({fileio.describe_os_error(exc)})") from None
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return [folder / n for n in names]


def write_files(folder: Path, asset: Asset) -> list:
    names = [OBJ, MTL, GLB]
    png = None
    if asset.texture is not None:
        png = np.round(fileio.srgb(asset.texture) * 255).astype(np.uint8)
        fileio.write_png(folder / PNG, png)
        names.insert(2, PNG)
    for name, texels in asset.maps.items():
        grey = np.round(texels * 255).astype(np.uint8)
        fileio.write_png(folder / PBR_PNG[name], np.repeat(grey[..., None], 3, axis=-1))
        names.insert(-1, PBR_PNG[name])
    mr = metallic_roughness(asset)
    if mr is not None:
        fileio.write_png(folder / MR_PNG, mr)
        names.insert(-1, MR_PNG)
    write_obj(folder / OBJ, folder / MTL, asset)
    write_glb(folder / GLB, asset, png, mr)
    if asset.environment is not None:
        fileio.write_rgb_exr(folder / ENV, asset.environment)
        names.append(ENV)
    record = {**asset.record, "files": names + [RECORD], "texture": PNG if png is not None else None,
              "base_color": None if png is not None else list(asset.color), "notes": asset.notes}
    fileio.write_json(folder / RECORD, record)
    return names + [RECORD]


def write_obj(path: Path, mtl: Path, asset: Asset):
    """OBJ (one vertex per position/UV pair, ``vt`` with v up the image) and its MTL."""
    lines = ["# psdr export", f"mtllib {mtl.name}", "usemtl material"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in asset.V]
    if asset.uv is not None:
        lines += [f"vt {u:.9g} {1 - v:.9g}" for u, v in asset.uv]
        lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in asset.F]
    else:
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in asset.F]
    kd = (1.0, 1.0, 1.0) if asset.texture is not None else asset.color
    material = ["newmtl material", "Ka 0 0 0", "Kd {:.6g} {:.6g} {:.6g}".format(*kd), "Ks 0 0 0", "Ns 1", "illum 1"]
    if asset.texture is not None:
        material.append(f"map_Kd {PNG}")
    for name, key in (("roughness", "Pr"), ("metallic", "Pm")):  # the MTL's PBR extension
        material.append(f"map_{key} {PBR_PNG[name]}" if name in asset.maps else f"{key} {getattr(asset, name):.6g}")
    with fileio.atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    with fileio.atomic_path(mtl) as tmp:
        tmp.write_text("\n".join(material) + "\n")


def metallic_roughness(asset: Asset):
    """The glTF metallic-roughness texture (H, W, 3) uint8 when roughness or metallic is a texture:
    G roughness, B metallic (a value recovered as a number fills its channel; the smaller texture
    is resampled bilinearly to the larger one's size), R unused (0); else None."""
    if not asset.maps:
        return None
    H, W = max((m.shape for m in asset.maps.values()), key=lambda s: s[0] * s[1])
    def channel(name):
        m = asset.maps.get(name)
        if m is None:
            return np.full((H, W), getattr(asset, name))
        return m if m.shape == (H, W) else np.asarray(Image.fromarray(m.astype(np.float32)).resize((W, H), Image.BILINEAR))
    out = np.stack([np.zeros((H, W)), channel("roughness"), channel("metallic")], -1)
    return np.round(np.clip(out, 0, 1) * 255).astype(np.uint8)


def write_glb(path: Path, asset: Asset, png, mr=None):
    """Binary glTF 2.0 through trimesh: a metallic-roughness material (metallic 0, roughness 1 unless
    recovered; with ``mr``, the metallic-roughness texture and factors 1)."""
    textures = {}
    if png is not None:
        textures["baseColorTexture"] = Image.fromarray(png)
    else:
        textures["baseColorFactor"] = [*asset.color, 1.0]
    if mr is not None:
        textures["metallicRoughnessTexture"] = Image.fromarray(mr)
    material = trimesh.visual.material.PBRMaterial(
        name="material", metallicFactor=1.0 if mr is not None else asset.metallic,
        roughnessFactor=1.0 if mr is not None else asset.roughness, **textures)
    if asset.uv is not None:
        uv = np.column_stack([asset.uv[:, 0], 1.0 - asset.uv[:, 1]])  # trimesh's (OBJ) convention; flipped back in glTF
        visual = trimesh.visual.TextureVisuals(uv=uv, material=material)
    else:
        visual = trimesh.visual.TextureVisuals(material=material)
    mesh = trimesh.Trimesh(asset.V, asset.F, visual=visual, process=False)
    data = trimesh.exchange.gltf.export_glb(trimesh.Scene(mesh), include_normals=False)
    with fileio.atomic_path(path) as tmp:
        tmp.write_bytes(data)
