"""Remeshing never ends a run: defective remesher output is detected and falls back."""
from pathlib import Path

import numpy as np
import pymeshlab

from psdr_cli.geometry import remesh
from psdr_cli.scene import meshes

#: An optimised shape (iteration 200 of a smooth-shaded run) on which Instant Meshes + MeshLab's
#: repair produced non-2-manifold faces and MeshLab's orientation filter raised, killing the run.
CRASH = Path(__file__).parent / "data" / "remesh_crash_iter0200.ply"


def test_defects_names_what_is_wrong_with_a_mesh():
    V, F = meshes.sphere(1.0, subdivisions=2)
    assert remesh.defects(V, F) == []
    assert any("open edges" in d for d in remesh.defects(V, F[1:]))
    flipped = F.copy()
    flipped[0] = flipped[0, ::-1]
    assert any("inconsistent face orientation" in d for d in remesh.defects(V, flipped))
    bad = V.copy()
    bad[0] = np.nan
    assert remesh.defects(bad, F) == ["non-finite vertices"]


def test_the_mesh_that_crashed_a_run_remeshes_to_a_clean_surface():
    V, F = meshes.read_mesh_file(CRASH)
    warnings = []
    V2, F2 = remesh.remesh(V, F, 2500, "instant", warn=warnings.append)
    assert remesh.defects(V2, F2) == []
    assert 1500 < len(V2) < 4000
    assert all("remesh (instant" in w for w in warnings)


def test_when_every_remesher_fails_the_input_mesh_is_kept(monkeypatch):
    def broken(*args, **kwargs):
        raise pymeshlab.PyMeshLabException("Failed to apply filter: meshing_re_orient_faces_coherently")

    monkeypatch.setattr(remesh, "instant_meshes", broken)
    monkeypatch.setattr(remesh, "isotropic", broken)
    V, F = meshes.sphere(1.0, subdivisions=2)
    warnings = []
    V2, F2 = remesh.remesh(V, F, 500, "instant", warn=warnings.append)
    assert np.array_equal(V2, V) and np.array_equal(F2, F)
    assert len(warnings) == 2 and "keeping the current mesh" in warnings[-1]
    assert "PyMeshLabException" in warnings[0]
