"""Where an optimisation's target images come from, one source per module, each declaring its
``SOURCE`` (:class:`.source.TargetSource`): :mod:`.rendered_mesh` (rendered from a ground-truth
mesh, the default), :mod:`.exr_files` (EXR files written by ``psdr render``) and
:mod:`.camera_dataset` (the photographs of a camera dataset). :mod:`.registry` lists them.
:mod:`.visual_hull` carves the camera dataset's initial shape (no source of its own)."""
