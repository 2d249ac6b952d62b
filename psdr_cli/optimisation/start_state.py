"""What an optimisation fits and where it starts: the target images from their source
(:mod:`psdr_cli.target_sources`: rendered from a ground-truth mesh and cached in the run folder,
EXR files from ``psdr render``, or the photographs of a camera dataset) and the initial shape.
Reads the experiment and the sources; writes the initial shape as the run's checkpoint 0."""
from __future__ import annotations

import math
import warnings

import numpy as np

from ..config.optimize_section import needs_uv, unwrap_size
from ..errors import PsdrError, PsdrWarning
from ..experiment.dataset_frame import to_dataset, to_normalised
from ..geometry import atlas
from ..geometry.remesh import remesh
from ..run_folder.checkpoints import write_mesh
from ..run_folder.layout import RunFiles
from ..run_folder.state import State
from ..scene import meshes
from ..target_sources.registry import target_source
from ..target_sources.source import TargetInputs
from .camera_refinement import refines_cameras
from .silhouette_alignment import aligned_corrections, aligned_views


def read_targets(exp, fresh: bool = False) -> TargetInputs:
    """:class:`TargetInputs` of a run from its source (:mod:`psdr_cli.target_sources`), read and
    checked (``preview_views`` included) without writing anything: a bad input fails before the
    run folder is touched. ``fresh``: also the initial shape (a resumed run starts from its saved
    state): the source's own, else ``init`` or a sphere around the ground truth."""
    source = target_source(exp.optimize)
    inputs = source.read(exp)
    views = len(inputs.images) if inputs.images is not None else len(exp.scene.cameras)
    bad = [v for v in exp.optimize.preview_views if v >= views]
    if bad:
        raise PsdrError(f"{exp.file}: optimize.preview_views: view {bad[0]} does not exist (0..{views - 1})")
    if not fresh:
        return inputs
    values = None
    if aligns_poses(exp, inputs):  # the hull is carved, and the loop starts, with poses the masks agree on
        cams = exp.optimize.cameras
        values = aligned_corrections(inputs.views, cams.rotation, cams.translation, math.radians(cams.max_rotation_deg))
        inputs = inputs._replace(views=aligned_views(inputs.views, values))
        turned = np.degrees(np.linalg.norm(values["camera_rotation"], axis=1))
        if turned.max() > 0:
            warnings.warn(f"optimize.cameras: the {len(turned)} views turned by up to {turned.max():.2f}° (median "
                          f"{np.median(turned):.2f}°) so that their masks agree before the visual hull is carved; "
                          f"the loop refines them from there", PsdrWarning, stacklevel=2)
    initial = source.initial(exp, inputs)
    return inputs._replace(initial=initial if initial is not None else initial_shape_uv(exp, inputs.reference),
                           initial_values=values)


def aligns_poses(exp, inputs: TargetInputs) -> bool:
    """Whether a fresh run's poses are registered to its masks before the hull is carved: the
    cameras are refined (``optimize.cameras``), the shape starts as the hull (no ``init``) and
    every view has a mask."""
    cfg = exp.optimize
    views = inputs.views or []
    return (cfg.init is None and len(views) > 1 and all(v.mask is not None for v in views)
            and refines_cameras(cfg.cameras, len(views), cfg.target_dataset is not None, exp.estimator.engine,
                                exp.file))


def load_targets(exp, files: RunFiles, inputs: TargetInputs):
    """(target images, cameras or None, ground truth (V, F) or None) of a run, from its source
    (rendered targets are cached in ``targets/``, the ground truth written as ``reference.ply``)."""
    return target_source(exp.optimize).load(exp, files, inputs), inputs.cameras, inputs.reference


def initial_state(exp, files: RunFiles, shape, warn, values: dict | None = None) -> State:
    """The state of a fresh run from its initial shape (V, F, UV or None: :func:`initial_shape_uv`),
    remeshed (``remesh.initial``) unless ``remesh.method: none``, written as checkpoint 0, with the
    starting ``values`` of other unknowns (:attr:`TargetInputs.initial_values`)."""
    cfg = exp.optimize
    V, F, uv = shape
    if cfg.remesh.method != "none":
        if uv is not None:  # split at UV seams: the remeshers want one vertex per position
            V, F = meshes.weld_vertices(V, F)
        V, F = remesh(V, F, cfg.remesh.initial, cfg.remesh.method, warn=warn)
        uv = None
        if needs_uv(cfg):  # the textures start uniform: new UVs suffice
            try:
                V, F, uv = atlas.unwrap(V, F, unwrap_size(cfg))
            except Exception as exc:  # noqa: BLE001 - xatlas failed on the remeshed initial shape
                raise PsdrError(f"{exp.file}: optimize: no UV atlas for the textures on the remeshed initial shape "
                                f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None
    write_mesh(files.checkpoint(0), dataset_coordinates(exp, V), F, uv)
    return State(0, V, F, uv=uv, values=dict(values or {}))


def dataset_coordinates(exp, V):
    """Vertices ``V`` in the coordinates the user gave: a dataset's own (``V`` is in its normalised
    frame: :mod:`psdr_cli.experiment.dataset_frame`), else the scene's (unchanged)."""
    dataset = exp.optimize.target_dataset
    return to_dataset(V, dataset.frame if dataset else None)


def initial_shape(exp, reference):
    """(V, F) of ``init`` (with its transform), or a sphere around the reference's bounding box."""
    return initial_shape_uv(exp, reference)[:2]


def initial_shape_uv(exp, reference):
    """(V, F, UV or None) of the initial shape (:func:`initial_shape`); with a recovered texture the
    default sphere is a UV sphere, and a given ``init`` must have UVs. With a camera dataset an
    ``init`` mesh file (and its transform) is in the dataset's coordinates, like the meshes a run
    writes (so a run can start from another's ``final.ply``); a procedural shape is in the
    normalised frame, where the object has about unit size (:mod:`psdr_cli.experiment.dataset_frame`)."""
    cfg = exp.optimize
    texture = needs_uv(cfg)
    if cfg.init is not None:
        V, F, uv = meshes.load_mesh_uv(cfg.init, str(exp.file), keep_uv=texture)
        if texture and uv is None:
            raise PsdrError(f"{exp.file}: optimize.init.mesh: has no UV coordinates, which a recovered texture "
                            f"needs (e.g. {{shape: sphere, resolution: 16, uv: true}}, or an OBJ with 'vt')")
        V = meshes.apply_transform(V, meshes.transform_matrix(cfg.init_transform))
        if cfg.target_dataset and cfg.init.file is not None:  # a mesh file is in the dataset's coordinates
            V = to_normalised(V, cfg.target_dataset.frame)
        return V, F, uv
    if reference is None:
        raise PsdrError(f"{exp.file}: optimize.init: required when the targets are images "
                        f"(e.g. init: {{mesh: {{shape: sphere, radius: 0.5}}}})")
    V, F = reference
    lo, hi = V.min(0), V.max(0)
    radius = 0.5 * float((hi - lo).max())
    Vs, Fs, uv = meshes.uv_sphere(radius, 16) if texture else (*meshes.sphere(radius=radius, subdivisions=3), None)
    return Vs + (lo + hi) / 2, Fs, uv


