#!/usr/bin/env python
"""A photograph dataset that psdr did not render: Mitsuba's own ``path`` integrator draws a
published mesh (the Stanford bunny inside the pymeshlab wheel) under a known environment map
(``scenes/studio.exr``) from cameras on a sphere, and writes the same views in two formats:

- **Blender / NeRF-synthetic** (``blender/``): ``transforms_train.json`` and ``transforms_test.json``
  (``camera_angle_x``, camera-to-world ``transform_matrix`` in OpenGL axes), straight-alpha RGBA
  PNGs (8-bit sRGB, alpha = coverage), as Blender writes them with a transparent film;
- **COLMAP text model** (``colmap/``): ``sparse/0/{cameras,images,points3D}.txt`` (a PINHOLE
  camera; world-to-camera rotations as quaternions, OpenCV axes), JPEGs of the object over a
  backdrop (``images/``) and mask PNGs (``masks/``, named ``<image name>.png``).

The object sits in an arbitrary frame (``--scale``, ``--offset``), and the held-out views are
every ``--holdout``-th camera (index mod k = 0, as ``holdout_every`` splits). Also writes ``ground_truth.ply`` (the mesh in the dataset's
coordinates) and ``dataset.json`` (what made it).

Mitsuba renders with ``hide_emitters`` and an RGBA film: its RGB is the premultiplied colour α·C,
so the straight colour of a Blender PNG is C = RGB / α where α > 0.

With ``--mesh FILE`` (PLY or OBJ) that mesh replaces the bunny: taken as z-up, centred in x/y,
resting on z = 0, its longest side ``--scale`` (as the bunny is placed); ``--reflectance`` sets
its diffuse colour and ``--max-depth`` the path integrator's depth.

    .venv/bin/python benchmarks/photo_dataset.py --out runs/photo_dataset --views 40 --size 128
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import mitsuba as mi
import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def camera_poses(count: int, centre, radius: float, seed: int) -> list:
    """Camera-to-world 4×4 matrices (OpenCV axes: x right, y down, z forward) on a sphere of
    ``radius`` around ``centre`` (elevations −15°…60°, Fibonacci azimuths), looking at ``centre``
    with z up."""
    rng = np.random.default_rng(seed)
    poses = []
    for i in range(count):
        azimuth = math.radians(137.508 * i + rng.uniform(-5, 5))
        elevation = math.radians(-15 + 75 * ((i * 0.618034) % 1.0))
        d = np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                      math.sin(elevation)])
        origin = np.asarray(centre) + radius * d
        forward = -d
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        M = np.eye(4)
        M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = right, down, forward, origin
        poses.append(M)
    return poses


def mitsuba_sensor(cam_to_world: np.ndarray, fov_deg: float, size: int, spp: int) -> dict:
    """A Mitsuba perspective sensor with the pose of an OpenCV camera (Mitsuba's camera space:
    x left, y up, z forward, so to_world = M · diag(−1, −1, 1, 1))."""
    to_world = cam_to_world @ np.diag([-1.0, -1.0, 1.0, 1.0])
    return {"type": "perspective", "fov": fov_deg, "fov_axis": "x", "to_world": mi.ScalarTransform4f(to_world),
            "film": {"type": "hdrfilm", "width": size, "height": size, "pixel_format": "rgba",
                     "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": spp}}


def render_views(V, F, poses, fov_deg: float, size: int, spp: int, envmap: Path, reflectance,
                 max_depth: int = 4, bsdf: dict | None = None, vertex_colors=None) -> list:
    """(H, W, 4) premultiplied RGBA renders of every pose by Mitsuba's ``path`` integrator.

    By default the object is diffuse with the constant ``reflectance``. ``bsdf`` (a Mitsuba BSDF
    dictionary) replaces that material; ``vertex_colors`` ((n, 3) linear RGB, one per vertex of
    ``V``) are attached to the mesh as the attribute ``vertex_color``, which such a BSDF can read
    with ``{"type": "mesh_attribute", "name": "vertex_color"}`` (a texture without UVs)."""
    mesh = mi.Mesh("object", len(V), len(F))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.ravel(V).astype(np.float32))
    params["faces"] = mi.UInt32(np.ravel(F).astype(np.uint32))
    params.update()
    if vertex_colors is not None:
        mesh.add_attribute("vertex_color", 3, mi.Float(np.ravel(vertex_colors).astype(np.float32)))
    if bsdf is None:
        bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(reflectance)}}
    mesh.set_bsdf(mi.load_dict(bsdf))
    images = []
    for i, pose in enumerate(poses):
        scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": max_depth,
                                                                "hide_emitters": True},
                              "sensor": mitsuba_sensor(pose, fov_deg, size, spp),
                              "env": {"type": "envmap", "filename": str(envmap), "scale": 0.8,
                                      "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], 90)},
                              "object": mesh})
        images.append(np.asarray(mi.render(scene, seed=i), np.float64))
    return images


def placed(V, size: float):
    """``V`` centred in x/y, resting on z = 0, its longest side ``size`` (as ``meshes.bunny``)."""
    V = np.asarray(V, np.float64)
    lo, hi = V.min(0), V.max(0)
    return (V - [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]]) * (size / (hi - lo).max())


def srgb8(linear: np.ndarray) -> np.ndarray:
    x = np.clip(linear, 0.0, 1.0)
    return np.round(255 * np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)).astype(np.uint8)


def straight(rgba: np.ndarray) -> tuple:
    """(straight colour C, α) of a premultiplied RGBA image."""
    alpha = np.clip(rgba[..., 3], 0.0, 1.0)
    colour = np.where(alpha[..., None] > 1e-6, rgba[..., :3] / np.maximum(alpha[..., None], 1e-6), 0.0)
    return colour, alpha


def write_blender(out: Path, images, poses, fov_deg: float, holdout: int):
    """The Blender / NeRF-synthetic layout (module docstring)."""
    (out / "train").mkdir(parents=True, exist_ok=True)
    (out / "test").mkdir(parents=True, exist_ok=True)
    splits = {"train": [], "test": []}
    for i, (rgba, pose) in enumerate(zip(images, poses)):
        split = "test" if i % holdout == 0 else "train"  # as holdout_every k holds views out
        colour, alpha = straight(rgba)
        pixels = np.concatenate([srgb8(colour), np.round(255 * alpha)[..., None].astype(np.uint8)], -1)
        name = f"{split}/r_{i:03d}"
        mi.Bitmap(pixels, pixel_format=mi.Bitmap.PixelFormat.RGBA).write(str(out / f"{name}.png"))
        opengl = pose @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV → OpenGL camera axes (y up, z backward)
        splits[split].append({"file_path": f"./{name}", "transform_matrix": opengl.tolist()})
    for split, frames in splits.items():
        text = json.dumps({"camera_angle_x": math.radians(fov_deg), "frames": frames}, indent=1)
        (out / f"transforms_{split}.json").write_text(text)


def quaternion(R: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix (Shepperd's method, w ≥ 0)."""
    w = math.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2, R[2, 1] - R[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2, R[0, 2] - R[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2, R[1, 0] - R[0, 1])
    q = np.array([w, x, y, z])
    return q / np.linalg.norm(q)


def write_colmap(out: Path, images, poses, fov_deg: float, size: int, backdrop):
    """The COLMAP text layout (module docstring): JPEGs over ``backdrop`` and mask PNGs."""
    for sub in ("sparse/0", "images", "masks"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    f = size / (2 * math.tan(math.radians(fov_deg) / 2))
    (out / "sparse/0/cameras.txt").write_text(f"# Camera list\n1 PINHOLE {size} {size} {f!r} {f!r} {size / 2!r} {size / 2!r}\n")
    lines = ["# Image list: IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then POINTS2D"]
    for i, (rgba, pose) in enumerate(zip(images, poses)):
        colour, alpha = straight(rgba)
        composite = alpha[..., None] * colour + (1 - alpha[..., None]) * np.asarray(backdrop)
        name = f"img_{i:03d}.jpg"
        mi.Bitmap(srgb8(composite), pixel_format=mi.Bitmap.PixelFormat.RGB).write(str(out / "images" / name))
        mi.Bitmap(np.round(255 * alpha).astype(np.uint8)[..., None],
                  pixel_format=mi.Bitmap.PixelFormat.Y).write(str(out / "masks" / f"{name}.png"))
        R = pose[:3, :3].T
        t = -R @ pose[:3, 3]
        q = quaternion(R)
        lines.append(f"{i + 1} {' '.join(repr(float(v)) for v in q)} {' '.join(repr(float(v)) for v in t)} 1 {name}")
        lines.append("")
    (out / "sparse/0/images.txt").write_text("\n".join(lines) + "\n")
    (out / "sparse/0/points3D.txt").write_text("# 3D point list (empty)\n")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "photo_dataset")
    ap.add_argument("--views", type=int, default=40)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--fov", type=float, default=35.0)
    ap.add_argument("--holdout", type=int, default=8, help="every k-th view (index mod k = 0) is a test view")
    ap.add_argument("--scale", type=float, default=3.0, help="the object's size in the dataset's frame")
    ap.add_argument("--offset", type=float, nargs=3, default=[4.0, -2.0, 1.0])
    ap.add_argument("--faces", type=int, default=5000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--mesh", type=Path, default=None, help="a PLY or OBJ mesh instead of the bunny")
    ap.add_argument("--reflectance", type=float, nargs=3, default=[0.7, 0.6, 0.5])
    ap.add_argument("--max-depth", type=int, default=4, help="the path integrator's max_depth")
    args = ap.parse_args(argv)
    mi.set_variant("llvm_ad_rgb")
    from psdr_cli.scene.meshes import bunny, read_mesh_file, write_ply  # the product's mesh loaders (not its renderer)
    if args.mesh is None:
        V, F = bunny(size=args.scale, faces=args.faces)
    else:
        V, F = read_mesh_file(args.mesh)
        V, F = placed(V, args.scale), np.asarray(F, np.int64)
    V = V + np.asarray(args.offset)
    centre = V.mean(0)
    radius = args.scale / (2 * math.tan(math.radians(args.fov) / 2)) * 1.25
    poses = camera_poses(args.views, centre, radius, args.seed)
    images = render_views(V, F, poses, args.fov, args.size, args.spp, ROOT / "scenes" / "studio.exr",
                          tuple(args.reflectance), args.max_depth)
    args.out.mkdir(parents=True, exist_ok=True)
    write_blender(args.out / "blender", images, poses, args.fov, args.holdout)
    write_colmap(args.out / "colmap", images, poses, args.fov, args.size, (0.35, 0.4, 0.3))
    write_ply(args.out / "ground_truth.ply", V, F)
    (args.out / "dataset.json").write_text(json.dumps({**{k: (str(v) if isinstance(v, Path) else v)
                                                          for k, v in vars(args).items()},
                                                       "renderer": f"mitsuba path, max_depth {args.max_depth}",
                                                       "envmap": "scenes/studio.exr, scale 0.8, rotated 90° about x"},
                                                      indent=1))
    print(f"wrote {args.views} views ({args.size}²) to {args.out}/blender and {args.out}/colmap")


if __name__ == "__main__":
    main()
