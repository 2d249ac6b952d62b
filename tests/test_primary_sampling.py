"""Edge density of the primary boundary term (``estimator.primary_sampling``).

On a finely tessellated flat-shaded mesh almost all projected edge length lies on inner creases,
across which the radiance jumps only by the turn of the facet normal; ``jump`` samples those
edges in proportion to that turn (clamped, psdr_cli.estimators.primary) and so spends more of
the samples on silhouettes. Both densities estimate the same integral: the gradient images must
agree (image sum and 4×4 tiles), and ``jump`` must have the lower variance on such a mesh.
(Agreement with finite differences, with the default ``jump``, is checked on the same dense blob
in test_real_mesh_gradients.py.)
"""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from psdr_cli import api
from psdr_cli.config.options import with_estimator
from psdr_cli.estimators.primary import JUMP_ANGLE, JUMP_MIN_WEIGHT, jump_weights, stratified
from psdr_cli.rendering.reference import block_sums, mean_and_error
from psdr_cli.support import backend
from standins import blob_cfg, bumpy_blob, load
from psdr_cli.geometry.topology import build_topology

#: passes of one sample per pixel each: the variance ratio below is heavy-tailed (rare large
#: 1/w_e draws), so it needs many (16 passes gave 1.16-2.58 over five seeds, 128 give 1.46-1.85)
PASSES = 128


def primary_passes(exp, sampling: str) -> np.ndarray:
    """PASSES independent primary-term gradient images (n, H, W, 3) with ``sampling``."""
    est = api.gradient_images(with_estimator(exp, primary_sampling=sampling), terms=["primary"],
                              min_passes=PASSES)["primary"]
    return np.asarray(est.passes, np.float64)


@pytest.fixture(scope="module")
def dense_blob_passes(tmp_path_factory):
    """The flat bumpy blob at 2562 vertices (32², 128 passes of 1 spp) under both densities."""
    exp = load(blob_cfg(False, spp=(16, PASSES, 16)), tmp_path_factory.mktemp("blob"), {"blob": bumpy_blob(4)})
    return {s: primary_passes(exp, s) for s in ("length", "jump")}


def z_scores(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(mean_a − mean_b) / sqrt(se_a² + se_b²) of two stacks of independent estimates."""
    ma, sa = mean_and_error(a)
    mb, sb = mean_and_error(b)
    return (ma - mb) / np.maximum(np.sqrt(sa ** 2 + sb ** 2), 1e-12)


def test_jump_and_length_densities_agree(dense_blob_passes):
    """Same expectation: image sum |z| < 3, and |z| < 4 on every 4×4 tile."""
    a, b = dense_blob_passes["jump"], dense_blob_passes["length"]
    assert abs(z_scores(a.sum((1, 2, 3)), b.sum((1, 2, 3)))) < 3
    tiles = z_scores(block_sums(a, 4), block_sums(b, 4))
    assert np.abs(tiles).max() < 4, np.round(tiles, 1)


def test_jump_density_lowers_the_variance_on_a_dense_flat_mesh(dense_blob_passes):
    """Summed per-pixel variance at least 1.3× lower with ``jump`` (1.46-1.85× over five seeds;
    uniform length sampling is 1×)."""
    var = {s: p.var(0, ddof=1).sum() for s, p in dense_blob_passes.items()}
    assert var["length"] > 1.3 * var["jump"], var


def test_jump_weights_follow_the_facet_turn():
    """w_e = clamp(φ_e / JUMP_ANGLE, JUMP_MIN_WEIGHT, 1) on inner creases of a flat mesh, 1 on
    silhouettes and on every edge of a smooth-shaded mesh."""
    V, F = bumpy_blob(2)
    topo = build_topology(V, F)
    rows = np.arange(len(topo))
    inner = np.ones(len(rows), bool)
    inner[::2] = False
    w = jump_weights(topo, V, rows, inner, smooth=False)
    n0, n1 = topo.normals(V)
    phi = np.arccos(np.clip(np.einsum("ij,ij->i", n0, n1), -1, 1))
    assert np.allclose(w[inner], np.clip(phi[inner] / JUMP_ANGLE, JUMP_MIN_WEIGHT, 1), atol=1e-6)
    assert (w[~inner] == 1).all()
    assert (jump_weights(topo, V, rows, inner, smooth=True) == 1).all()
    assert w[inner].min() < 1  # the blob's fine creases are sampled less densely than its silhouette


def test_curve_draws_are_stratified_per_view():
    """``stratified``: lane j of each view's N lanes draws in [j/N, (j + 1)/N), whatever the view,
    and every stratum gets one lane (so the draws over a view cover the curve list evenly)."""
    backend.select_variant("auto")
    n, views = 500, 3
    rng = np.random.default_rng(5)
    u = mi.Float(rng.uniform(0, 1, n * views).astype(np.float32))
    view = dr.arange(mi.UInt32, n * views) // n
    x = np.asarray(stratified(u, n, view)).reshape(views, n)
    j = np.arange(n)
    assert np.all((x >= j / n) & (x < (j + 1) / n))
    one = np.asarray(stratified(mi.Float(np.asarray(u)[:n]), n))
    assert np.allclose(one, x[0]) and np.all(one < 1.0)
