#!/usr/bin/env python
"""The optimisation loop's per-iteration geometry work (the worker thread of
:mod:`psdr_cli.optimisation.geometry_ahead`), side by side in one process: the edge table
(:func:`psdr_cli.estimators.boundary_sampling.edge_rows`) built from scratch (the face parts of
:mod:`psdr_cli.geometry.topology` forgotten before every build) against built with the face parts
remembered (the loop's case between remeshes), and the intersection search for scale.

On the CPU this work overlaps the iteration's kernels; on the GPU the kernels are short and the
loop waits for it (docs/benchmarks/gpu_first_run.md: 19 ms of an 87 ms iteration). The shapes are
``configs/reconstruct_bunny.yaml``'s initial sphere remeshed to ``--vertices`` (the loop's sizes
before and after its remesh). Calls alternate between the two settings; ``reference`` is a
10⁷-step Python loop in the same process.

    .venv/bin/python benchmarks/edge_table.py [--vertices 800,2500] [--repeats 30] [--json docs/benchmarks/edge_table.json]
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import drjit as dr  # noqa: E402
from iteration_time import setup  # noqa: E402
from machine import reference_loop_seconds as reference_loop  # noqa: E402

from psdr_cli.estimators.boundary_sampling import camera_origins, edge_rows  # noqa: E402
from psdr_cli.estimators.primary import mesh_arrays, mesh_shapes  # noqa: E402
from psdr_cli.geometry import topology  # noqa: E402
from psdr_cli.geometry.intersections import intersection_segments  # noqa: E402


def timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def measure(vertices: int, repeats: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        exp, _, problem, _, _, _ = setup(1, Path(tmp), vertices)
        scene, chains = problem.scene, exp.estimator.chains
        cameras = camera_origins(scene.mi_scene)
        objects = dict(scene.objects)
        names = [n for n, om in objects.items() if om.edges]
        shapes = mesh_shapes(scene.mi_scene, names)
        arrays = mesh_arrays([dr.detach(s.vertex_positions_buffer()) for s in shapes],
                             [s.faces_buffer() for s in shapes])

        def rows():
            return edge_rows(objects, cameras, exp.estimator.edge_sort, chains.max_turn, chains.max_length)

        def fresh():
            topology._FACE_PARTS.clear()
            return rows()

        def search():
            return intersection_segments([V for V, _ in arrays], [F for _, F in arrays])

        rows(), search()   # warm-up (imports, first allocations)
        times = {"fresh": [], "remembered": [], "intersection_search": []}
        for _ in range(repeats):
            times["fresh"].append(timed(fresh))
            rows()   # the face parts remembered again
            times["remembered"].append(timed(rows))
            times["intersection_search"].append(timed(search))
        problem.release()
        out = {k: statistics.median(v) for k, v in times.items()}
        out["vertices"] = int(sum(len(V) for V, _ in arrays))
        out["faces"] = int(sum(len(F) for _, F in arrays))
        return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--vertices", default="800,2500", help="remesh targets of the initial shape")
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    result = {"python": platform.python_version(), "reference_before": reference_loop(), "shapes": []}
    for n in (int(v) for v in args.vertices.split(",")):
        r = measure(n, args.repeats)
        result["shapes"].append(r)
        print(f"{r['vertices']} vertices, {r['faces']} faces: edge table {r['fresh'] * 1e3:.2f} ms from scratch, "
              f"{r['remembered'] * 1e3:.2f} ms with the face parts remembered "
              f"({r['remembered'] / r['fresh']:.2f}x); intersection search {r['intersection_search'] * 1e3:.2f} ms")
    result["reference_after"] = reference_loop()
    print(f"reference loop (10⁷ steps): {result['reference_before']:.3f} s before, {result['reference_after']:.3f} s after")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
