"""The run-folder contract of ``psdr optimize``: what a run folder holds and how it is read,
one idea per module.

A run of an experiment lives in ``<output>/<name>/`` (with ``optimize.variants``: one folder per
variant, ``<output>/<name>/<label>/``) and holds

    run.json            fingerprint of the experiment the run belongs to (:func:`.record.run_record`)
    state.npz           everything needed to continue (written atomically after every iteration)
    log.csv             one row per completed iteration (:data:`.log.LOG_FIELDS`)
    checkpoints/        iter_NNNN.ply every ``checkpoint_every`` iterations (iter_0000: the start)
    previews/           target | current | |difference| strips of the preview views
    targets/            the target images (cached by a content hash)
    reference.ply       the ground truth the targets were rendered from (mesh targets only)
    final.ply, optimize.json, loss.png, chamfer.png   once the run has finished

Every file is written atomically (:func:`psdr_cli.support.fileio.atomic_path`) except ``log.csv``, which
is appended to and rewritten (atomically) up to the last saved iteration on resume; it is read
tolerantly (:func:`.log.read_log`: a torn or garbage tail is ignored with a warning).

While ``psdr optimize`` writes a run folder it holds an exclusive lock (:func:`.layout.lock_run`,
``fcntl.flock`` on ``.<name>.lock`` next to the folder, released by the OS when the process
ends); a second process is refused with the holder's PID.

Modules: :mod:`.layout` (the layout, the lock, moving a previous run aside), :mod:`.variants`
(one run per ``optimize.variants`` entry), :mod:`.fingerprint` and :mod:`.fingerprint_v1` (what a
run depends on), :mod:`.record` (run.json), :mod:`.log` (log.csv and the loss plot),
:mod:`.state` (state.npz and resuming), :mod:`.checkpoints` (meshes and previews),
:mod:`.target_cache` (the cached target images).
"""
