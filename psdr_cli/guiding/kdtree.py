"""Adaptive Kd-tree guide (paper §4.1, Algorithm 1), built from one or two batches of target samples.

The algorithm is docs/theory.md §5 ("Adaptive Kd-tree"). u1 is first cut at the given
breakpoints (edge or chain ends), so that x^B(u1) is continuous inside each interval. The target
F̃ is evaluated at a batch of uniform points, and optionally at a second batch drawn from a first
tree, every sample then weighted by the combined density, w(u) = 1 / (d₀(u) + N₁ g₁(u)). Each
batch is one Dr.Jit kernel launch, so a build costs about as much as F̃ at its samples. The tree
is grown level by level from these fixed weighted samples: a node whose weighted linear fit
F̃ ≈ a + b·(x − ½) leaves an error err_r = |B_r| · Σw|F̃ − fit| / Σw above threshold · Î is
split in half along the axis whose two half-box fits leave the smallest residual. Each leaf
holds the fit at its 8 corners (clamped at 0), blended with the mean of its u1 interval. A
``prior`` guide replaces the first batch and tree, so a refresh costs one batch;
:func:`fit_kdtree` grows a tree from given weighted samples without evaluating the target (the
optimisation loop's own samples, :mod:`.loop_fed`). Lookups walk the stored split planes from the
root (``dr.while_loop``).

Parameters (experiment keys)
----------------------------
Used when ``estimator.guiding`` is ``kdtree``, or ``auto`` picks it (:mod:`.auto`):

``estimator.kdtree.initial_samples`` (int in [0, 2²²], default 0)
    Target evaluations of the uniform batch; 0: half the lanes of one boundary pass,
    W·H·``boundary_spp``/2, clamped to [2¹⁷, 2¹⁸] (:func:`initial_samples`).
``estimator.kdtree.refine_ratio`` (float in [0, 16], default 0)
    Second batch of ``refine_ratio`` × ``initial_samples`` points drawn from a first tree;
    0: one batch.
``estimator.kdtree.samples_per_node`` (int in [4, 2¹⁶], default 32)
    A node is split only while it holds at least this many samples.
``estimator.kdtree.threshold`` (float ≥ 0, default 0.002)
    A node is split while err_r > threshold · Î (Î ≈ ∫F̃).
``estimator.kdtree.max_depth`` (int in [1, 64], default 24)
    Most splits below a u1 interval.
``estimator.kdtree.max_leaves`` (int in [1, 2²²], default 65536)
    Leaf budget; when it binds, the largest errors are split first.
``estimator.kdtree.interval_share`` (float in [0, 1], default 0.1)
    Share β of the u1 interval's mean blended into each leaf.
``estimator.kdtree.technique_share`` (float in [0, 1], default 0.3)
    MIS: share of the two techniques' common edge profile (:func:`share_profiles`).
``estimator.guide_epsilon`` (float in [0, 1], default 0.05)
    Uniform share ε of the guide (trees fitted in the loop: at least :data:`EXPLORE`, which is
    also the share with which a first tree or a prior places its samples).
``estimator.edge_sort`` (bool, default false)
    Breakpoints at chain ends instead of edge ends (:mod:`psdr_cli.geometry.edge_sort`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..support.jitarray import jit_array
from .guide import CORNERS, Guide, GuideKind, GuideStats

#: relative ridge keeping the small least-squares systems well posed
RIDGE = 1e-6
#: smallest uniform share of the guide that places the refinement samples
EXPLORE = 0.25


class KdTreeGuide(Guide):
    kind = "kdtree"

    def __init__(self, lo, hi, corners, epsilon, stats, nodes):
        """A guide over the leaves' boxes (``lo``, ``hi``) with trilinear ``corners`` values, a
        uniform share ``epsilon``, and the tree's node arrays ``nodes`` = (axis, split, child,
        leaf): an inner node's axis (−1 at a leaf), its split coordinate, its first child (the
        second follows it) and a leaf node's leaf index."""
        super().__init__(lo, hi, corners, epsilon, stats)
        axis, split, child, leaf = nodes
        self.axis, self.split, self.child, self.node_leaf = axis, split, child, leaf
        self._axis = jit_array(mi.Int32, axis)
        self._split = jit_array(mi.Float, split)
        self._child = jit_array(mi.UInt32, np.maximum(child, 0))
        self._leaf = jit_array(mi.UInt32, np.maximum(leaf, 0))

    def leaf_of(self, u: mi.Point3f) -> mi.UInt32:
        def body(node):
            ax = dr.gather(mi.Int32, self._axis, node)
            coord = dr.select(ax == 0, u.x, dr.select(ax == 1, u.y, u.z))
            right = coord >= dr.gather(mi.Float, self._split, node)
            return (dr.gather(mi.UInt32, self._child, node) + dr.select(right, 1, 0),)

        node = dr.while_loop((mi.UInt32(0),),
                             lambda node: dr.gather(mi.Int32, self._axis, node) >= 0, body,
                             labels=("node",), label="kdtree_lookup")[0]
        return dr.gather(mi.UInt32, self._leaf, node)

    def leaf_of_np(self, u: np.ndarray) -> np.ndarray:
        node = np.zeros(len(u), np.int64)
        while True:
            ax = self.axis[node]
            inner = ax >= 0
            if not inner.any():
                return self.node_leaf[node]
            coord = u[np.arange(len(u)), np.maximum(ax, 0)]
            nxt = self.child[node] + (coord >= self.split[node])
            node = np.where(inner, nxt, node)

    def memory_bytes(self) -> int:
        return super().memory_bytes() + 4 * 4 * len(self.axis)


def _node_sums(q, starts, M):
    """Per-node sums of the per-sample statistics q (M, S) for samples sorted by node, node k
    holding q[starts[k]:starts[k+1]] (empty nodes give 0)."""
    K = len(starts)
    if M == 0:
        return np.zeros((K, q.shape[1]))
    sums = np.add.reduceat(q, np.minimum(starts, M - 1), axis=0)
    ends = np.r_[starts[1:], M]
    return np.where((ends > starts)[:, None], sums, 0.0)


#: upper-triangle index pairs (i ≤ j) of the 4×4 normal matrix
TRIU = np.triu_indices(4)


def _statistics(x, f, w, n):
    """Per-sample sufficient statistics of a weighted linear fit f ≈ A·c with A = (1, x − ½):
    columns w·A_iA_j (i ≤ j, 10), w·A_i f (4), w f², n (samples represented) → (M, 16)."""
    A = np.concatenate([np.ones((len(x), 1)), x - 0.5], axis=1)
    wA = w[:, None] * A
    return np.concatenate([wA[:, TRIU[0]] * A[:, TRIU[1]], wA * f[:, None], (w * f * f)[:, None],
                           n[:, None]], axis=1)


def _solve(sums):
    """Least-squares coefficients c (K, 4) and residual sum of squares Σw(f − A·c)² (K,) from
    node sums of :func:`_statistics`."""
    AtA = np.empty((len(sums), 4, 4))
    AtA[:, TRIU[0], TRIU[1]] = sums[:, :10]
    AtA[:, TRIU[1], TRIU[0]] = sums[:, :10]
    Atf, ff = sums[:, 10:14], sums[:, 14]
    ridge = RIDGE * (np.trace(AtA, axis1=1, axis2=2)[:, None, None] + 1e-30) * np.eye(4)
    coef = np.linalg.solve(AtA + ridge, Atf[..., None])[..., 0]
    rss = ff - 2 * np.einsum("ki,ki->k", coef, Atf) + np.einsum("ki,kij,kj->k", coef, AtA, coef)
    return coef, np.maximum(rss, 0.0)


def _corner_values(coef, mean):
    """Fit at the 8 box corners, clamped at 0, rescaled so their mean equals the sample mean."""
    c = np.maximum(coef[:, :1] + coef[:, 1:] @ (CORNERS - 0.5).T, 0.0)
    avg = c.mean(axis=1)
    scale = np.where(avg > 0, mean / np.where(avg > 0, avg, 1.0), 0.0)
    c = c * scale[:, None]
    return np.where((avg > 0)[:, None], c, mean[:, None])


def blend_interval_mean(lo, hi, corners, breaks, share: float):
    """(1 − share)·corners + share·(mean of the fit over the leaf's u1 interval)."""
    if share <= 0 or len(corners) == 0:
        return corners
    k = np.clip(np.searchsorted(breaks, 0.5 * (lo[:, 0] + hi[:, 0])) - 1, 0, len(breaks) - 2)
    mass = np.prod(hi - lo, axis=1) * corners.mean(axis=1)
    mean = np.bincount(k, mass, minlength=len(breaks) - 1) / np.diff(breaks)
    return (1.0 - share) * corners + share * mean[k][:, None]



def interval_profile(guide, breaks) -> tuple:
    """(share of the guide's mass M in each u1 interval of ``breaks`` (sums to 1), interval of
    each leaf)."""
    k = np.clip(np.searchsorted(breaks, 0.5 * (guide.lo[:, 0] + guide.hi[:, 0]), side="right") - 1,
                0, len(breaks) - 2)
    mass = np.bincount(k, guide.mass, minlength=len(breaks) - 1)
    return mass / max(mass.sum(), 1e-300), k


def share_profiles(guides: dict, breaks, share: float) -> dict:
    """MIS guides over the same u1 with a common edge profile: each technique's leaf values
    become (1 − share) f + share · M · p̄_k / |interval k|, p̄ the mean of the techniques' interval
    mass shares. u1 (the edge point) means the same for every technique, so an edge that one
    technique's samples found (e.g. light sampling towards a small emitter) is not left to the
    uniform share ε by another (wedge sampling, whose non-zero directions there are rare)."""
    trees = {t: g for t, g in guides.items() if g.kind == "kdtree" and g.total > 0}
    if share <= 0 or len(trees) < 2:
        return guides
    breaks = np.unique(np.clip(np.r_[0.0, np.asarray(breaks, np.float64), 1.0], 0.0, 1.0))
    profiles = {t: interval_profile(g, breaks) for t, g in trees.items()}
    mean = np.mean([p for p, _ in profiles.values()], axis=0) / np.diff(breaks)
    out = dict(guides)
    for t, g in trees.items():
        corners = (1.0 - share) * g.corners + share * g.total * mean[profiles[t][1]][:, None]
        out[t] = KdTreeGuide(g.lo, g.hi, corners, g.epsilon, g.stats, tree_nodes(g))
    return out


def interval_counts(breaks, n: int, minimum: int) -> np.ndarray:
    """Uniform samples per u1 interval: ∝ its length, at least ``minimum``."""
    return np.maximum(minimum, np.round(n * np.diff(breaks)).astype(np.int64))


def uniform_batch(rng, breaks, counts):
    """counts[k] uniform points in the slab of interval k: (u (M,3), density d₀ (M,))."""
    k = np.repeat(np.arange(len(counts)), counts)
    width = np.diff(breaks)
    u = rng.random((len(k), 3))
    u[:, 0] = breaks[k] + u[:, 0] * width[k]
    return u, (counts / width)[k]


def uniform_density(u, breaks, counts):
    """d₀(u) = n_k / |interval k| of the uniform batch at arbitrary points u."""
    k = np.clip(np.searchsorted(breaks, u[:, 0], side="right") - 1, 0, len(counts) - 1)
    return (counts / np.diff(breaks))[k]


def evaluate(target, u):
    """F̃(u) ≥ 0 as float64, non-finite values set to 0."""
    f = np.asarray(target(u), np.float64)
    return np.where(np.isfinite(f), np.abs(f), 0.0)


def interval_tree(breaks):
    """Top of the tree: balanced cuts of u1 at ``breaks``. Returns the node arrays (axis, split,
    child, leaf) and the interval nodes (ids, lo, hi) the growth starts from."""
    axis, split, child = [-1], [0.0], [-1]
    ids, lo, hi = [], [], []
    queue = [(0, 0, len(breaks) - 1)]
    while queue:
        node, i0, i1 = queue.pop()
        if i1 - i0 == 1:
            ids.append(node)
            lo.append([breaks[i0], 0.0, 0.0])
            hi.append([breaks[i1], 1.0, 1.0])
            continue
        mid = (i0 + i1) // 2
        c = len(axis)
        axis[node], split[node], child[node] = 0, breaks[mid], c
        axis += [-1, -1]; split += [0.0, 0.0]; child += [-1, -1]
        queue += [(c, i0, mid), (c + 1, mid, i1)]
    nodes = (np.array(axis), np.array(split, np.float64), np.array(child), np.full(len(axis), -1))
    order = np.argsort(np.array(lo)[:, 0], kind="stable")
    return nodes, np.array(ids)[order], np.array(lo)[order], np.array(hi)[order]


class Growth:
    """The tree under construction: node arrays (axis, split, child, leaf; −1 = none) and the
    leaves found so far (boxes, corner values)."""

    def __init__(self, nodes):
        self.axis, self.split, self.child, self.leaf = (a.copy() for a in nodes)
        self.lo, self.hi, self.corners, self.deepest = [], [], [], 0

    def add_leaves(self, ids, lo, hi, corners, depth):
        self.leaf[ids] = np.arange(len(self.lo), len(self.lo) + len(ids))
        self.lo += list(lo); self.hi += list(hi); self.corners += list(corners)
        if len(depth):
            self.deepest = max(self.deepest, int(depth.max()))

    def split_nodes(self, parents, lo, hi, axis):
        """Split ``parents`` (boxes lo, hi) in half along ``axis``: the children's (ids, lo, hi),
        the two children of parent i at 2i (low half) and 2i + 1."""
        rows = np.arange(len(parents))
        mid = 0.5 * (lo[rows, axis] + hi[rows, axis])
        first = len(self.axis) + 2 * rows
        self.axis[parents], self.split[parents], self.child[parents] = axis, mid, first
        n = 2 * len(parents)
        self.axis = np.r_[self.axis, np.full(n, -1)]
        self.split = np.r_[self.split, np.zeros(n)]
        self.child = np.r_[self.child, np.full(n, -1)]
        self.leaf = np.r_[self.leaf, np.full(n, -1)]
        h_left, l_right = hi.copy(), lo.copy()
        h_left[rows, axis] = mid
        l_right[rows, axis] = mid
        return (np.stack([first, first + 1], 1).ravel(), np.stack([lo, l_right], 1).reshape(-1, 3),
                np.stack([h_left, hi], 1).reshape(-1, 3))


def regroup(group, keep_nodes, child_side=None):
    """Sample selection and new node index after keeping the nodes ``keep_nodes`` (K,) of a
    level; with ``child_side`` (per sample) node k's samples go to child 2·rank(k) + side."""
    rank = np.cumsum(keep_nodes) - 1
    sel = keep_nodes[group]
    new = rank[group] if child_side is None else 2 * rank[group] + child_side
    return sel, new[sel]


@dataclass(frozen=True)
class TreeLimits:
    """When a node stops splitting: it holds fewer than ``samples_per_node`` samples, its fit's
    error is at most ``threshold`` × the total, it is ``max_depth`` deep, or the tree has
    ``max_leaves`` leaves."""
    samples_per_node: int = 32
    threshold: float = 0.002
    max_depth: int = 24
    max_leaves: int = 65536


def tree_nodes(guide: "KdTreeGuide") -> tuple:
    """(axis, split, child, leaf): the node arrays of ``guide``."""
    return guide.axis, guide.split, guide.child, guide.node_leaf


def grow(top, breaks, samples, limits: TreeLimits):
    """Grow the tree below the u1 intervals (``top``: :func:`interval_tree`) from fixed weighted
    ``samples`` = (u, f, w, n), each standing for n samples (step 3 of the module docstring), up
    to ``limits``. Returns the :class:`Growth`."""
    u, f, w, n = samples
    samples_per_node, threshold, max_depth, max_leaves = (limits.samples_per_node, limits.threshold,
                                                          limits.max_depth, limits.max_leaves)
    nodes, ids, lo, hi = top
    tree = Growth(nodes)
    sg = np.clip(np.searchsorted(breaks, u[:, 0], side="right") - 1, 0, len(ids) - 1)
    su, sf, sw, sn = u, f, w, n
    depth = np.zeros(len(ids), np.int64)
    total = None
    while len(ids):
        # nodes without a non-zero sample are zero leaves; their samples leave the fit
        zero = np.bincount(sg, sf, minlength=len(ids)) <= 0
        if zero.any():
            tree.add_leaves(ids[zero], lo[zero], hi[zero], np.zeros((int(zero.sum()), 8)), depth[zero])
            sel, sg = regroup(sg, ~zero)
            su, sf, sw, sn = su[sel], sf[sel], sw[sel], sn[sel]
            ids, lo, hi, depth = ids[~zero], lo[~zero], hi[~zero], depth[~zero]
            if not len(ids):
                break
        order = np.argsort(sg, kind="stable")
        su, sf, sw, sn, sg = su[order], sf[order], sw[order], sn[order], sg[order]
        K, M = len(ids), len(sg)
        starts = np.searchsorted(sg, np.arange(K))
        x = (su - lo[sg]) / (hi - lo)[sg]
        q = _statistics(x, sf, sw, sn)
        sums = _node_sums(q, starts, M)
        coef, _ = _solve(sums)
        wsum, count = sums[:, 0], sums[:, 15]
        vol = np.prod(hi - lo, axis=1)
        mean = sums[:, 10] / np.maximum(wsum, 1e-300)
        if total is None:
            total = float((vol * mean).sum())
        resid = np.abs(sf - coef[sg, 0] - np.einsum("mi,mi->m", x - 0.5, coef[sg, 1:]))
        err = vol * _node_sums((sw * resid)[:, None], starts, M)[:, 0] / np.maximum(wsum, 1e-300)
        want = (err > threshold * total) & (depth < max_depth) & (count >= samples_per_node)
        budget = max_leaves - (len(tree.lo) + K)  # every split adds one leaf
        if want.sum() > budget:
            keep = np.argsort(-np.where(want, err, -1.0))[:max(budget, 0)]
            want = np.zeros(K, bool)
            want[keep] = True
        done = ~want
        if done.any():
            tree.add_leaves(ids[done], lo[done], hi[done], _corner_values(coef[done], mean[done]), depth[done])
        if not want.any():
            break
        best = split_axes(q, x, sg, want, sums)
        ids, lo, hi = tree.split_nodes(ids[want], lo[want], hi[want], best[want])
        sel, sg = regroup(sg, want, x[np.arange(M), best[sg]] >= 0.5)
        su, sf, sw, sn = su[sel], sf[sel], sw[sel], sn[sel]
        depth = np.repeat(depth[want] + 1, 2)
    return tree


def split_axes(q, x, group, want, sums):
    """Per node (K,), the axis whose two half-box fits leave the smallest weighted residual sum of
    squares; computed for the ``want`` nodes only (others get 0)."""
    sel = want[group]
    q, x, g = q[sel], x[sel], np.cumsum(want)[group[sel]] - 1
    starts = np.searchsorted(g, np.arange(int(want.sum())))
    total = sums[want]
    rss = np.stack([_solve(low)[1] + _solve(total - low)[1] for low in
                    (_node_sums(q * (x[:, a:a + 1] < 0.5), starts, len(g)) for a in range(3))], 1)
    best = np.zeros(len(want), np.int64)
    best[want] = np.argmin(rss, axis=1)
    return best


def make_tree(top, breaks, samples, limits: TreeLimits, *, epsilon: float, interval_share: float):
    """KdTreeGuide grown up to ``limits`` from weighted ``samples`` = (u, f, w), each standing for
    one sample, leaves blended with their interval's mean."""
    u, f, w = samples
    n = np.ones(len(f))
    t = grow(top, breaks, (u, f, w * n, n), limits)
    lo, hi = np.array(t.lo), np.array(t.hi)
    corners = blend_interval_mean(lo, hi, np.array(t.corners), breaks, interval_share)
    stats = GuideStats("kdtree", max_depth=t.deepest, intervals=len(breaks) - 1)
    return KdTreeGuide(lo, hi, corners, epsilon, stats, (t.axis, t.split, t.child, t.leaf))


def explorer(guide: KdTreeGuide) -> KdTreeGuide:
    """The same tree with a uniform share of at least ``EXPLORE`` (places refinement samples)."""
    return KdTreeGuide(guide.lo, guide.hi, guide.corners, max(guide.epsilon, EXPLORE), GuideStats("kdtree"),
                       tree_nodes(guide))


def leaf_breaks(breaks, max_leaves: int) -> np.ndarray:
    """The u1 cuts of the tree's top: 0, ``breaks``, 1 (sorted, unique), thinned to at most
    max_leaves/2 intervals by merging neighbours."""
    breaks = np.unique(np.clip(np.r_[0.0, np.asarray(breaks, np.float64), 1.0], 0.0, 1.0))
    if len(breaks) - 1 > max_leaves // 2:
        breaks = breaks[np.unique(np.linspace(0, len(breaks) - 1, max_leaves // 2 + 1).round().astype(int))]
    return breaks


def fit_kdtree(u, f, w, *, breaks=(0.0, 1.0), limits: TreeLimits = TreeLimits(), epsilon: float = 0.01,
               interval_share: float = 0.1) -> KdTreeGuide:
    """Kd-tree guide grown (step 3 of the module docstring) up to ``limits`` from given samples
    u (N,3) with target values F̃ (N,) and weights w (N,), Σ_{u∈B} w F̃ ≈ ∫_B F̃: no target
    evaluation."""
    t0 = time.perf_counter()
    breaks = leaf_breaks(breaks, limits.max_leaves)
    samples = (np.asarray(u, np.float64), np.asarray(f, np.float64), np.asarray(w, np.float64))
    guide = make_tree(interval_tree(breaks), breaks, samples, limits, epsilon=epsilon, interval_share=interval_share)
    guide.stats.evaluations = 0
    guide.stats.memory_bytes = guide.memory_bytes()
    guide.stats.build_seconds = time.perf_counter() - t0
    return guide


def tree_arrays(guide: KdTreeGuide) -> dict:
    """The arrays that define ``guide`` (for a saved optimisation state), in float32 and int32."""
    return {"lo": guide.lo.astype(np.float32), "hi": guide.hi.astype(np.float32),
            "corners": guide.corners.astype(np.float32), "axis": guide.axis.astype(np.int32),
            "split": guide.split.astype(np.float32), "child": guide.child.astype(np.int32),
            "leaf": guide.node_leaf.astype(np.int32), "epsilon": np.array([guide.epsilon])}


def tree_from_arrays(a: dict) -> KdTreeGuide:
    """The guide :func:`tree_arrays` described (the same guide for a tree that went through
    :func:`tree_arrays` before)."""
    stats = GuideStats("kdtree")
    nodes = (np.asarray(a["axis"], np.int64), np.asarray(a["split"], np.float64),
             np.asarray(a["child"], np.int64), np.asarray(a["leaf"], np.int64))
    guide = KdTreeGuide(np.asarray(a["lo"], np.float64), np.asarray(a["hi"], np.float64),
                        np.asarray(a["corners"], np.float64), float(np.ravel(a["epsilon"])[0]), stats, nodes)
    stats.memory_bytes = guide.memory_bytes()
    return guide


def build_kdtree(target, breaks=(0.0, 1.0), *, limits: TreeLimits = TreeLimits(), epsilon: float = 0.01,
                 seed: int = 0, initial_samples: int = 32768, interval_share: float = 0.1,
                 refine_ratio: float = 2.0, min_interval_samples: int = 4, prior=None) -> KdTreeGuide:
    """Kd-tree guide of ``target`` (numpy u (N,3) → F̃ ≥ 0 (N,)), u1 pre-split at ``breaks``,
    grown up to ``limits`` from two batches of F̃ (one with a ``prior`` guide; see the module
    docstring)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    breaks = leaf_breaks(breaks, limits.max_leaves)
    top = interval_tree(breaks)
    n1 = int(round(refine_ratio * initial_samples))
    if prior is not None:
        u, g = explorer(prior).sample_np(initial_samples + n1, rng)
        f = evaluate(target, u)
        w = 1.0 / ((initial_samples + n1) * g)
    else:
        counts = interval_counts(breaks, initial_samples, min_interval_samples)
        u, d0 = uniform_batch(rng, breaks, counts)
        f = evaluate(target, u)
        w = 1.0 / d0
        if n1 > 0 and f.any():
            first = explorer(make_tree(top, breaks, (u, f, w), limits, epsilon=epsilon, interval_share=interval_share))
            u2, g2 = first.sample_np(n1, rng)
            f = np.r_[f, evaluate(target, u2)]
            w = 1.0 / np.r_[d0 + n1 * first.pdf_batch(u), uniform_density(u2, breaks, counts) + n1 * g2]
            u = np.r_[u, u2]
    guide = make_tree(top, breaks, (u, f, w), limits, epsilon=epsilon, interval_share=interval_share)
    stats = guide.stats
    stats.evaluations = len(f)
    stats.memory_bytes = guide.memory_bytes()
    stats.build_seconds = time.perf_counter() - t0
    return guide


#: automatic first Kd-tree batch: lanes of one boundary pass / AUTO_SHARE, within AUTO_RANGE
AUTO_SHARE = 2
AUTO_RANGE = (131072, 262144)


def initial_samples(estimator, pixels: int) -> int:
    """The Kd-tree's first batch: ``kdtree.initial_samples``, or when it is 0 (auto)
    pixels · boundary_spp / AUTO_SHARE clamped to AUTO_RANGE, so that both batches together
    ((1 + refine_ratio) × this) cost a fixed share of one boundary pass."""
    n = estimator.kdtree.initial_samples
    return n if n > 0 else int(np.clip(pixels * estimator.boundary_spp // AUTO_SHARE, *AUTO_RANGE))


def build_kdtree_guide(target, breaks, estimator, seed: int, pixels: int) -> KdTreeGuide:
    """A Kd-tree guide of ``estimator.kdtree``'s settings (:class:`~.guide.GuideKind`)."""
    k = estimator.kdtree
    return build_kdtree(target, breaks, limits=tree_limits(k), epsilon=estimator.guide_epsilon, seed=seed,
                        initial_samples=initial_samples(estimator, pixels), interval_share=k.interval_share,
                        refine_ratio=k.refine_ratio)


def tree_limits(kdtree) -> TreeLimits:
    """The :class:`TreeLimits` of an ``estimator.kdtree`` section."""
    return TreeLimits(kdtree.samples_per_node, kdtree.threshold, kdtree.max_depth, kdtree.max_leaves)


KIND = GuideKind("kdtree", build_kdtree_guide, loop_fed=True)
