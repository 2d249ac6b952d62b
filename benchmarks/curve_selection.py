#!/usr/bin/env python
"""Time of the primary term's numpy curve selection (``primary.primary_edge_ids``) for a batch of
four views of the demo's experiment, with each edge row's face normals computed inside every
call (once per view) or once per pass and shared by the views (``primary.mesh_normals``, what
the term does), at the initial shape (872 vertices) and at 2562 vertices; medians of 12 repeats.

    .venv/bin/python benchmarks/curve_selection.py [--json docs/benchmarks/curve_selection.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402
from iteration_time import setup  # noqa: E402
from machine import reference_loop_seconds  # noqa: E402

from psdr_cli.estimators import primary  # noqa: E402
from psdr_cli.estimators.boundary_sampling import edge_list  # noqa: E402
from psdr_cli.estimators.camera import Projection  # noqa: E402

VIEWS = (0, 3, 6, 9)


def selection_ms(initial: int | None, repeats: int = 12) -> dict:
    """Median milliseconds of the four views' selections, normals per call and shared."""
    with tempfile.TemporaryDirectory() as tmp:
        exp, _, problem, settings, _, _ = setup(1, Path(tmp), initial)
        problem.apply()
        obj = problem.scene.objects[exp.optimize.object]
        obj.vertices, obj.faces = problem.vertices(), problem.F
        edges = edge_list(problem.scene, settings.estimator, False)
        V = np.asarray(dr.detach(edges.positions(mi.traverse(problem.scene.mi_scene))), np.float64).reshape(-1, 3)
        origins = [np.asarray(dr.detach(Projection(problem.scene.sensors[v]).origin), np.float64).reshape(-1)[:3]
                   for v in VIEWS]
        per_call, shared = [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            for o in origins:
                primary.primary_edge_ids(edges, V, o, True, "length")
            t1 = time.perf_counter()
            normals = primary.mesh_normals(edges, V)
            for o in origins:
                primary.primary_edge_ids(edges, V, o, True, "length", normals)
            shared.append(time.perf_counter() - t1)
            per_call.append(t1 - t0)
        problem.release()
        return {"vertices": len(V), "normals per view ms": 1e3 * float(np.median(per_call)),
                "normals once ms": 1e3 * float(np.median(shared))}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    out = {"reference_before": reference_loop_seconds(), "runs": [selection_ms(None), selection_ms(2500)]}
    out["reference_after"] = reference_loop_seconds()
    for r in out["runs"]:
        print(r)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
