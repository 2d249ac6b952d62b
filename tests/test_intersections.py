"""Broad phase of the intersection-curve search (:mod:`psdr_cli.geometry.intersections`)."""
import numpy as np

from psdr_cli.geometry.intersections import intersection_segments, overlapping_pairs, sorted_unique
from psdr_cli.scene import meshes


def all_pairs(lo, hi):
    """Every overlapping pair (i < j) by testing all n² pairs, in lexicographic order."""
    hit = np.all((lo[:, None] <= hi[None]) & (lo[None] <= hi[:, None]), axis=-1)
    i, j = np.nonzero(np.triu(hit, 1))
    return i, j


def test_grid_broad_phase_finds_every_overlapping_pair():
    """Small boxes of very different sizes and a few huge ones (a floor's triangles): the grid
    finds exactly the pairs that the all-pairs test finds, in the same order."""
    rng = np.random.default_rng(3)
    centre = rng.random((1500, 3))
    size = 0.03 * rng.lognormal(0.0, 1.0, (1500, 3))
    size[:5] = [[3.0, 3.0, 0.001]] * 5        # huge boxes through everything
    size[5:8] = 0.0                           # points
    lo, hi = centre - size, centre + size
    expected = all_pairs(lo, hi)
    found = overlapping_pairs(lo, hi)
    assert len(expected[0]) > 1500
    assert np.array_equal(found[0], expected[0]) and np.array_equal(found[1], expected[1])


def test_sorted_unique_is_numpys_unique():
    rng = np.random.default_rng(5)
    for a in (rng.integers(0, 50, 400), np.zeros(0, np.int64), np.array([7]), np.array([3, 3, 3])):
        assert np.array_equal(sorted_unique(a), np.unique(a)) and sorted_unique(a).dtype == np.unique(a).dtype


def test_no_pairs_for_separate_boxes_and_tiny_inputs():
    lo = np.arange(10, dtype=float)[:, None] * np.ones(3)
    assert len(overlapping_pairs(lo, lo + 0.5)[0]) == 0
    assert len(overlapping_pairs(lo[:1], lo[:1] + 1)[0]) == 0


def test_segments_through_a_large_floor():
    """A sphere sunk halfway through a two-triangle floor: the curve is the sphere's equator,
    found although the floor's triangles are far larger than the grid's cells."""
    V, F = meshes.sphere(radius=0.5, subdivisions=3)
    floor = np.array([[-5, -5, 0.013], [5, -5, 0.013], [5, 5, 0.013], [-5, 5, 0.013]])
    seg = intersection_segments([V, floor], [F, np.array([[0, 1, 2], [0, 2, 3]])])
    assert len(seg) > 40 and set(np.unique(seg.mesh[:, 1])) == {1}
