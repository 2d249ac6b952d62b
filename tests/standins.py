"""Procedural stand-ins for published meshes, with the features that make their gradients hard
(dense bumpy surfaces, intersecting shells, a moving camera), shared by
``tests/test_real_mesh_gradients.py`` and ``benchmarks/gradients.py``:

- a dense bumpy blob (flat or smooth-shaded) over a floor, lit from the side; cut open into a
  dome, or sunk into the floor; a coarse smooth dome under the studio environment map and an
  area light;
- a smooth lens whose rim folds its faces back by more than 90° (as Blender's Suzanne does at its
  brows and ears), stood on edge under the same environment map and area light;
- a head with an eye: one mesh of two intersecting shells (flat, or smooth-shaded and lit from
  the side; translated or turned about the vertical);
- a moving camera over a box, a ball and a floor;
- meshes with non-manifold edges or faces turned over, as exported by CAD tools and scanners:
  a cube with every third triangle turned, a book of pages on one spine with mixed winding, two
  boxes sharing an edge with one of them inside out.

Each ``*_cfg`` returns an experiment dictionary (32×32 px; :func:`envmap_dome_cfg` 24×24); :func:`load` writes it, with any
procedural meshes as PLY files, into a folder and loads it as an :class:`Experiment`.
"""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import yaml

from psdr_cli.config.experiment_file import Experiment
from psdr_cli.experiment.load import load_experiment
from psdr_cli.scene import meshes

LIGHT_SIDE = {"type": "area", "center": [1.6, 0.3, 1.2], "normal": [-0.8, -0.1, -0.3], "size": [0.5, 0.5],
              "radiance": 20}
FLOOR = {"name": "floor", "mesh": {"shape": "plane", "size": 4}, "edges": False}
#: The studio environment map that ships with the repository (read through its path).
STUDIO = Path(__file__).resolve().parents[1] / "scenes" / "studio.exr"


def bumpy_blob(subdivisions=3, radius=0.45, amplitude=0.08):
    """An icosphere with smooth radial bumps (642 vertices at 3 subdivisions): concave and convex
    edges, a fine silhouette."""
    V, F = meshes.sphere(radius, subdivisions)
    u = V / np.linalg.norm(V, axis=1, keepdims=True)
    bump = amplitude * (np.sin(3 * u[:, 0] + 1) * np.cos(2 * u[:, 1]) + 0.5 * np.sin(4 * u[:, 2]))
    return V + u * bump[:, None], F


def open_dome(subdivisions=3):
    """The bumpy blob's upper part, cut open below z = −0.15: a smooth open mesh with a ragged
    boundary and both of its sides in view."""
    V, F = bumpy_blob(subdivisions)
    return V, F[(V[F][:, :, 2] > -0.15).all(axis=1)]


def folded_lens(radius=0.5, height=0.15, segments=12, rings=2):
    """A closed lens: two caps z = ±height·(1 − (r/radius)²) of ``rings`` rings of ``segments``
    vertices each (72 faces by default) meeting at a sharp rim, where the faces' normals are 118°
    apart. Smooth-shaded, the rim's vertex normals point outwards in the rim's plane, 59° from
    either face, and a ray spawned from a face within (1 + max|p|)·RayEpsilon·(−n_a·n_b) of the
    rim starts beyond the other face's plane: the ray-spawn band of a folded edge, which the
    procedural domes and blobs (all edges under 90°) do not have."""
    V = [[0.0, 0.0, height], [0.0, 0.0, -height]]
    ring = {}
    for side in (1, -1):
        for i in range(1, rings + 1):
            r = radius * i / rings
            for j in range(segments):
                if i == rings and side == -1:  # the rim is shared by both caps
                    ring[side, i, j] = ring[1, i, j]
                    continue
                phi = 2 * np.pi * (j + 0.5 * (i % 2)) / segments
                ring[side, i, j] = len(V)
                V.append([r * np.cos(phi), r * np.sin(phi), side * height * (1 - (r / radius) ** 2)])
    F = []
    for side, pole in ((1, 0), (-1, 1)):
        tris = [[pole, ring[side, 1, j], ring[side, 1, (j + 1) % segments]] for j in range(segments)]
        for i in range(1, rings):
            for j in range(segments):
                a, b = ring[side, i, j], ring[side, i, (j + 1) % segments]
                c, d = ring[side, i + 1, j], ring[side, i + 1, (j + 1) % segments]
                tris += [[a, c, d], [a, d, b]] if i % 2 == 0 else [[a, c, b], [b, c, d]]
        F += tris if side == 1 else [t[::-1] for t in tris]  # outward on both caps
    return np.array(V, float), np.array(F)


def resting_blob():
    """The bumpy blob lowered until it sinks 0.02 into the floor plane (z = 0 after the
    experiment's translation): a contact curve between the object and the floor."""
    V, F = bumpy_blob()
    return V - np.array([0.0, 0.0, 0.6 + V[:, 2].min() + 0.02]), F


def head_with_eye(subdivisions=2):
    """One mesh, two shells: a sphere and a smaller one piercing it towards the camera (icospheres
    of 162 vertices each at 2 subdivisions, 42 at 1)."""
    V1, F1 = meshes.sphere(0.45, subdivisions)
    V2, F2 = meshes.sphere(0.2, subdivisions)
    V2 = V2 + np.array([0.12, -0.38, 0.12])
    return np.vstack([V1, V2]), np.vstack([F1, F2 + len(V1)])


def turn_faces(F, faces):
    """F with the triangles ``faces`` (an index or slice) turned over (winding reversed)."""
    F = np.array(F)
    F[faces] = F[faces, ::-1]
    return F


def turned_cube(size=0.5):
    """A cube with every third triangle turned over: a closed mesh whose winding is inconsistent
    (the turned triangles render black from outside with a one-sided material)."""
    V, F = meshes.cube((size, size, size))
    return V, turn_faces(F, slice(None, None, 3))


def book():
    """Three two-triangle pages on one spine (the x axis): an edge with three faces; the middle
    page is turned over, so the pages' windings disagree."""
    V = np.array([[-0.35, 0, 0], [0.35, 0, 0], [-0.35, -0.4, 0.15], [0.35, -0.4, 0.15],
                  [-0.35, -0.1, 0.42], [0.35, -0.1, 0.42], [-0.35, 0.35, 0.2], [0.35, 0.35, 0.2]])
    F = np.array([[0, 1, 3], [0, 3, 2], [0, 5, 1], [0, 4, 5], [0, 1, 7], [0, 7, 6]])
    return V, turn_faces(F, slice(2, 4))


def joined_boxes(size=0.36):
    """Two cubes of one mesh sharing one edge (four faces on it), the second inside out."""
    Va, Fa = meshes.cube((size, size, size))
    Vb, Fb = meshes.cube((size, size, size))
    V = np.vstack([Va + [0, -size / 2, -size / 2], Vb + [0, size / 2, size / 2]])
    return V, np.vstack([Fa, turn_faces(Fb, slice(None)) + len(Va)])


def part_cfg() -> dict:
    """A mesh ``part`` (give it :func:`turned_cube`, :func:`book` or :func:`joined_boxes`) over the
    blob's floor and light, turned 20° about the vertical and translated along (0.6, 0.3, 0.75):
    a motion with no special direction (moved straight up, the cube's shadow edge sweeps the
    floor so slowly that finite differences see no change in some tiles, and estimate 0 ± 0)."""
    cfg = blob_cfg(False)
    obj = cfg["scene"]["objects"][0]
    obj.update(name="part", transform={"translate": [0.05, 0, 0.5], "rotate": {"axis": [0, 0, 1], "angle_deg": 20}})
    cfg.update(name="part", parameter={"object": "part", "kind": "translate", "axis": [0.6, 0.3, 0.75]})
    return cfg


def scene_cfg(name, objects, emitters, camera, parameter, spp=(64, 256, 256), max_depth=2) -> dict:
    """An experiment dictionary at 32×32 px with (interior, primary, boundary) sample counts."""
    return {"name": name, "output": "runs", "seed": 3,
            "scene": {"film": {"width": 32, "height": 32}, "max_depth": max_depth, "cameras": [camera],
                      "emitters": emitters, "objects": objects},
            "parameter": parameter,
            "estimator": {"spp": spp[0], "primary_spp": spp[1], "boundary_spp": spp[2]}}


def blob_cfg(smooth: bool, spp=(64, 256, 256)) -> dict:
    """The bumpy blob (mesh ``blob``: give it :func:`bumpy_blob`) over a floor, translated in x."""
    return scene_cfg("blob", [{"name": "blob", "mesh": {"shape": "sphere"}, "transform": {"translate": [0, 0, 0.6]},
                               "smooth": smooth, "bsdf": {"type": "diffuse", "reflectance": [0.7, 0.6, 0.5]}},
                              copy.deepcopy(FLOOR)],
                     [copy.deepcopy(LIGHT_SIDE)], {"origin": [0, -2.4, 1.2], "target": [0, 0, 0.45], "fov": 40},
                     {"object": "blob", "kind": "translate", "axis": [1, 0, 0]}, spp=spp)


def eye_cfg(smooth: bool = False, kind: str = "translate") -> dict:
    """The head (mesh ``head``: give it :func:`head_with_eye`) over a floor, translated in x
    (``kind`` "translate") or turned about the vertical axis through its bounding box's centre
    ("rotate", θ in radians).

    ``smooth``: the smooth-shaded head, lit from the side (a brighter copy of the blob's light, so
    that the terminator crosses the visible head and eye) under the same dim environment, and
    turned 10° about the vertical: the mesh is mirror-symmetric, and unturned its edges in the
    plane x = 0 project exactly onto the image's middle pixel boundary, where a pixel's derivative
    has a kink (one-sided values that central differences average). Its floor keeps its edges:
    the floor's far border (in view, at the horizon) hides part of the environment from the
    head's unlit side, and without its edges that moving occlusion has no boundary term (the
    left silhouette tile then sat 5–8 % above finite differences, on a flat plain sphere too)."""
    head = {"name": "head", "mesh": {"shape": "sphere"}, "transform": {"translate": [0, 0, 0.5]},
            "bsdf": {"type": "diffuse", "reflectance": [0.7, 0.6, 0.5]}}
    light = {"type": "area", "center": [-0.8, -1.2, 2.0], "normal": [0.3, 0.5, -0.8], "size": [0.8, 0.8],
             "radiance": 12}
    floor = copy.deepcopy(FLOOR)
    if smooth:
        head.update(smooth=True, transform={"translate": [0, 0, 0.5], "rotate": {"axis": [0, 0, 1], "angle_deg": 10}})
        light = dict(copy.deepcopy(LIGHT_SIDE), radiance=40)
        floor["edges"] = True
    return scene_cfg("eyes", [head, floor], [light, {"type": "constant", "radiance": 0.3}],
                     {"origin": [0, -2.4, 1.0], "target": [0, 0, 0.45], "fov": 40},
                     {"object": "head", "kind": kind, "axis": [1, 0, 0] if kind == "translate" else [0, 0, 1]},
                     spp=(1024, 256, 256))


def envmap_dome_cfg(kind: str = "translate", film: int = 24, spp=(512, 2048, 2048)) -> dict:
    """A smooth open shape (mesh ``dome``: give it :func:`open_dome`, e.g. ``open_dome(1)``, 44
    faces) over a floor (edges on) under ``scenes/studio.exr`` at scale 0.6 (its bright lamp low
    on the +x side) and one area light (above, in front, on the left), translated in x (``kind`` "translate") or
    turned about the vertical through its bounding box's centre ("rotate", θ in radians); a
    ``film``² image. As for the smooth head, the dome is turned 10° and the camera moved 0.031
    sideways, so that no mirror-symmetric edge projects onto a pixel boundary."""
    dome = {"name": "dome", "mesh": {"shape": "sphere"}, "smooth": True,
            "transform": {"translate": [0, 0, 0.6], "rotate": {"axis": [0, 0, 1], "angle_deg": 10}},
            "bsdf": {"type": "diffuse", "reflectance": [0.7, 0.6, 0.5]}}
    floor = dict(copy.deepcopy(FLOOR), edges=True)
    light = {"type": "area", "center": [-0.8, -1.2, 2.0], "normal": [0.3, 0.5, -0.8], "size": [0.8, 0.8],
             "radiance": 6}
    cfg = scene_cfg("envdome", [dome, floor], [light, {"type": "envmap", "file": str(STUDIO), "scale": 0.6}],
                    {"origin": [0.031, -2.4, 1.2], "target": [0.031, 0, 0.45], "fov": 40},
                    {"object": "dome", "kind": kind, "axis": [1, 0, 0] if kind == "translate" else [0, 0, 1]},
                    spp=spp)
    cfg["scene"]["film"] = {"width": film, "height": film}
    return cfg


def envmap_lens_cfg(kind: str = "rotate") -> dict:
    """:func:`envmap_dome_cfg` with its mesh (``dome``: give it :func:`folded_lens`) stood nearly on
    edge (turned 80° about (1, 0.3, 0)), so that the rim's faces look sideways, towards the
    environment's lamp, rather than down at the floor: light that leaks through the ray-spawn
    band below a rim face then reaches the environment (max_depth 2: the floor would read 0)."""
    cfg = envmap_dome_cfg(kind)
    cfg["scene"]["objects"][0]["transform"] = {"translate": [0, 0, 0.6],
                                               "rotate": {"axis": [1, 0.3, 0], "angle_deg": 80}}
    return cfg


def camera_cfg(kind: str = "translate") -> dict:
    """A camera translated in x or rotated about z over a box, a ball and a floor."""
    return scene_cfg("camera", [
        {"name": "box", "mesh": {"shape": "cube", "size": [0.5, 0.5, 0.5]},
         "transform": {"translate": [-0.3, 0.1, 0.25], "rotate": {"axis": [0, 0, 1], "angle_deg": 30}},
         "bsdf": {"type": "diffuse", "reflectance": [0.7, 0.5, 0.3]}},
        {"name": "ball", "mesh": {"shape": "sphere", "radius": 0.25, "subdivisions": 2},
         "transform": {"translate": [0.4, -0.2, 0.25]}, "bsdf": {"type": "diffuse", "reflectance": [0.3, 0.5, 0.7]}},
        {"name": "floor", "mesh": {"shape": "plane", "size": 2.4}, "edges": False,
         "bsdf": {"type": "diffuse", "reflectance": 0.6}}],
        [{"type": "area", "center": [-0.6, 0.4, 2.2], "normal": [0.3, 0, -1], "size": [0.6, 0.6], "radiance": 15},
         {"type": "constant", "radiance": 0.2}],
        {"origin": [0.2, -2.4, 1.3], "target": [0, 0, 0.3], "fov": 40},
        {"camera": 0, "kind": kind, "axis": [1, 0, 0] if kind == "translate" else [0, 0, 1]}, spp=(256, 256, 256))


def two_camera_cfg() -> dict:
    """The box, ball and floor of the camera stand-in seen by two cameras, 16 spp per term."""
    cfg = camera_cfg()
    second = copy.deepcopy(cfg["scene"]["cameras"][0])
    second.update(origin=[-1.9, -1.5, 1.6], target=[0.05, 0.0, 0.3])
    cfg["scene"]["cameras"].append(second)
    cfg["estimator"].update(spp=16, primary_spp=64, boundary_spp=64)
    return cfg


def tile_weights(height: int, width: int) -> list:
    """Per-pixel weights: the whole image, then each quarter."""
    out = [np.ones((height, width, 3))]
    for i in range(2):
        for j in range(2):
            w = np.zeros((height, width, 3))
            w[i * height // 2:(i + 1) * height // 2, j * width // 2:(j + 1) * width // 2] = 1
            out.append(w)
    return out


def off_axis(cfg: dict, dx: float = 0.031) -> dict:
    """``cfg`` with its camera moved sideways (origin and target) by ``dx``, out of the plane x = 0
    that holds icosphere edges: seen from x = 0 such an edge projects exactly onto the boundary
    between pixel columns 15 and 16, where the pixel value has a kink at θ = 0."""
    for key in ("origin", "target"):
        cfg["scene"]["cameras"][0][key][0] += dx
    return cfg


def load(cfg: dict, folder: Path, mesh_arrays: dict | None = None) -> Experiment:
    """Experiment from ``cfg`` with procedural meshes {object name: (V, F)} written next to it as
    PLY files in ``folder``."""
    folder = Path(folder)
    for name, (V, F) in (mesh_arrays or {}).items():
        path = folder / f"{cfg['name']}_{name}.ply"
        meshes.write_ply(path, V, F)
        next(o for o in cfg["scene"]["objects"] if o["name"] == name)["mesh"] = {"file": str(path)}
    path = folder / f"{cfg['name']}.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return load_experiment(path)
