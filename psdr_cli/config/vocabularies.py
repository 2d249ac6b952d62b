"""Every name a key or a command-line option accepts, defined once: the terms of dI/dθ, the guides,
the direction techniques, remeshers, engines, Mitsuba variants, and the kinds of emitters,
parameters, datasets, backgrounds and environment-map means."""
from __future__ import annotations

#: Terms of dI/dθ = interior + primary + direct + indirect (in this order).
TERMS = ("interior", "primary", "direct", "indirect")

#: Guide kinds: each names the module of psdr_cli/guiding that declares its ``KIND``
#: (:mod:`psdr_cli.guiding.kinds`).
GUIDE_KINDS = ("grid", "kdtree")

#: Boundary guides over the primary samples u (``auto``: chosen per term; ``none``: unguided).
GUIDINGS = ("auto", "none", *GUIDE_KINDS)

#: Direction techniques of the boundary terms (``mis``: both, balance heuristic).
SAMPLINGS = ("dir", "light", "mis")

#: Edge densities of the primary term (``estimator.primary_sampling``: estimators/primary.py).
PRIMARY_SAMPLINGS = ("length", "jump")

#: Remeshers (``none``: keep the mesh; a scheduled remesh then uses ``isotropic``).
REMESH_METHODS = ("instant", "isotropic", "none")

#: Renderers of an optimisation's gradient images (``mitsuba``: Mitsuba's projective integrators).
ENGINES = ("psdr", "mitsuba")

#: Mitsuba's projective integrators (``estimator.mitsuba_integrator``).
MITSUBA_INTEGRATORS = ("direct_projective", "prb_projective")

#: Mitsuba variants (``auto``: CUDA when present, else LLVM).
VARIANTS = ("auto", "llvm_ad_rgb", "cuda_ad_rgb")

#: Folders of ``<output>/<name>/`` that commands other than ``psdr optimize`` write.
COMMAND_FOLDERS = ("render", "grad", "compare", "guide_stats")

#: Emitter types (``scene.emitters[].type``).
EMITTER_TYPES = ("area", "envmap", "sky", "constant")

#: Kinds of the scalar parameter θ (``parameter.kind``).
PARAMETER_KINDS = ("translate", "rotate", "scale", "envmap_rotate", "focal")

#: Camera-dataset formats (``optimize.target.dataset.format``; ``auto``: found from the files).
DATASET_FORMATS = ("auto", "blender", "transforms", "colmap")

#: What camera rays that leave a dataset's scene see (``optimize.target.dataset.background``).
BACKGROUNDS = ("auto", "hidden", "visible")

#: Whether the training views' poses are refined (``optimize.cameras``; ``auto``: for camera datasets).
CAMERA_MODES = ("auto", "on", "off")

#: Whether an optimised environment map keeps its mean (``optimize.envmap.mean``).
ENVMAP_MEANS = ("auto", "fixed", "free")
