"""Adaptive Kd-tree guide (paper §4.1, Algorithm 1), built breadth-first.

u1 is first cut at the given breakpoints (edge or chain boundaries), so that x^B(u1) is
continuous inside each interval; a balanced binary tree over those cuts forms the top of the
tree. Below, every node r with box B_r is processed level by level, all active nodes at once:

1. draw new uniform points in each active box (``initial_samples`` spread over the first level,
   ``samples_per_node`` per node below) and evaluate F̃ at all of them in one batch; a node also
   keeps the earlier samples of its ancestors that fall inside it;
2. fit F̃ ≈ a + b·(x − ½) by least squares in the box's local coordinates x ∈ [0,1)³; the fit
   error is err_r = |B_r| · mean |F̃ − fit|;
3. if err_r > threshold · Î (Î = ∫F̃ estimated from the first level), the node is split in half
   along the axis whose two half-box fits (from the same samples) leave the smallest total error,
   i.e. the axis along which the parent's single fit is worst. Otherwise, or at ``max_depth``, or
   when ``max_leaves`` is reached (largest errors split first), it becomes a leaf whose corner
   values are the fit at the 8 corners, clamped at 0 and rescaled to the sample mean.
4. Every leaf's function is blended with the mean of F̃ over its u1 interval,
   f ← (1 − β) f + β · mass_interval / width_interval (β = ``interval_share``): inside an edge
   (or chain) that carries mass, a sub-region the samples missed keeps a density of at least β
   times the interval's average instead of only the global uniform share ε.

Lookups walk the stored split planes from the root (``dr.while_loop``).
"""
from __future__ import annotations

import time

import drjit as dr
import mitsuba as mi
import numpy as np

from .guide import CORNERS, Guide, GuideStats

#: relative ridge keeping the small least-squares systems well posed
RIDGE = 1e-6


class KdTreeGuide(Guide):
    kind = "kdtree"

    def __init__(self, lo, hi, corners, epsilon, stats, axis, split, child, leaf):
        super().__init__(lo, hi, corners, epsilon, stats)
        self.axis, self.split, self.child, self.node_leaf = axis, split, child, leaf
        self._axis = mi.Int32(axis.astype(np.int32))
        self._split = mi.Float(split.astype(np.float32))
        self._child = mi.UInt32(np.maximum(child, 0).astype(np.uint32))
        self._leaf = mi.UInt32(np.maximum(leaf, 0).astype(np.uint32))

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


def _fit(x, f, w, group, K):
    """Weighted least-squares fits f ≈ a + b·(x − ½), one per group: x (M,3) local positions,
    f, w (M,), group (M,) in [0, K) → coefficients (K,4) and |residual| per sample (M,)."""
    A = np.concatenate([np.ones((len(x), 1)), x - 0.5], axis=1)
    AtA = np.empty((K, 4, 4))
    Atf = np.empty((K, 4))
    for i in range(4):
        Atf[:, i] = np.bincount(group, w * A[:, i] * f, minlength=K)
        for j in range(i, 4):
            AtA[:, i, j] = AtA[:, j, i] = np.bincount(group, w * A[:, i] * A[:, j], minlength=K)
    ridge = RIDGE * (np.trace(AtA, axis1=1, axis2=2)[:, None, None] + 1e-30) * np.eye(4)
    coef = np.linalg.solve(AtA + ridge, Atf[..., None])[..., 0]
    resid = np.abs(f - np.einsum("mi,mi->m", A, coef[group]))
    return coef, resid


def _group_mean(values, group, K, w=None):
    w = np.ones_like(values) if w is None else w
    return np.bincount(group, values * w, minlength=K) / np.maximum(np.bincount(group, w, minlength=K), 1e-30)


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


def _new_samples(rng, lo, hi, counts):
    """counts[k] uniform points in box k: (u (M,3), group (M,))."""
    group = np.repeat(np.arange(len(counts)), counts)
    return lo[group] + rng.random((len(group), 3)) * (hi - lo)[group], group


def build_kdtree(target, breaks=(0.0, 1.0), samples_per_node: int = 32, threshold: float = 0.002,
                 max_depth: int = 24, max_leaves: int = 65536, epsilon: float = 0.01,
                 seed: int = 0, initial_samples: int = 0, interval_share: float = 0.1) -> KdTreeGuide:
    """Kd-tree guide of ``target`` (numpy u (N,3) → F̃ ≥ 0 (N,)), u1 pre-split at ``breaks``.

    The first level spends ``initial_samples`` evaluations (spread over the intervals ∝ their
    length, at least ``samples_per_node`` each); every later node adds ``samples_per_node`` new
    ones. A node also keeps the samples of its ancestors that fall inside it, so structure seen
    once is never forgotten by a child that happens to draw only zeros."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    breaks = np.unique(np.clip(np.r_[0.0, np.asarray(breaks, np.float64), 1.0], 0.0, 1.0))
    if len(breaks) - 1 > max_leaves // 2:  # too many intervals: merge neighbours, keep the budget
        breaks = breaks[np.unique(np.linspace(0, len(breaks) - 1, max_leaves // 2 + 1).round().astype(int))]
    axis, split, child, leaf = [-1], [0.0], [-1], [-1]
    # Top of the tree: balanced cuts of u1 at the breakpoints; each interval becomes an active node
    active_id, active_lo, active_hi = [], [], []
    queue = [(0, 0, len(breaks) - 1)]
    while queue:
        node, i0, i1 = queue.pop()
        if i1 - i0 == 1:
            active_id.append(node)
            active_lo.append([breaks[i0], 0.0, 0.0])
            active_hi.append([breaks[i1], 1.0, 1.0])
            continue
        mid = (i0 + i1) // 2
        c = len(axis)
        axis[node], split[node], child[node] = 0, breaks[mid], c
        axis += [-1, -1]; split += [0.0, 0.0]; child += [-1, -1]; leaf += [-1, -1]
        queue += [(c, i0, mid), (c + 1, mid, i1)]
    axis, split, child, leaf = (np.array(axis), np.array(split, np.float64), np.array(child), np.array(leaf))
    ids, lo, hi = np.array(active_id), np.array(active_lo), np.array(active_hi)
    depth = np.zeros(len(ids), np.int64)
    share = hi[:, 0] - lo[:, 0]
    counts = np.maximum(samples_per_node, np.round(initial_samples * share).astype(np.int64))
    su, sf, sg = np.empty((0, 3)), np.empty(0), np.empty(0, np.int64)
    leaf_lo, leaf_hi, leaf_c = [], [], []
    total, evaluations, deepest = None, 0, 0
    while len(ids):
        K = len(ids)
        u_new, g_new = _new_samples(rng, lo, hi, counts)
        f_new = np.asarray(target(u_new), np.float64)
        f_new = np.where(np.isfinite(f_new), np.abs(f_new), 0.0)
        evaluations += len(f_new)
        su, sf, sg = np.concatenate([su, u_new]), np.concatenate([sf, f_new]), np.concatenate([sg, g_new])
        x = (su - lo[sg]) / (hi - lo)[sg]
        vol = np.prod(hi - lo, axis=1)
        mean = _group_mean(sf, sg, K)
        if total is None:
            total = float((vol * mean).sum())
        coef, resid = _fit(x, sf, np.ones_like(sf), sg, K)
        err = vol * _group_mean(resid, sg, K)
        want = (err > threshold * total) & (depth < max_depth) & (mean > 0)
        # leaf budget: every split adds one leaf; split the largest errors first
        budget = max_leaves - (len(leaf_lo) + K)
        if want.sum() > budget:
            keep = np.argsort(-np.where(want, err, -1.0))[:max(budget, 0)]
            want = np.zeros(K, bool)
            want[keep] = True
        done = ~want
        if done.any():
            leaf[ids[done]] = np.arange(len(leaf_lo), len(leaf_lo) + int(done.sum()))
            leaf_lo += list(lo[done]); leaf_hi += list(hi[done])
            leaf_c += list(_corner_values(coef[done], mean[done]))
            deepest = max(deepest, int(depth[done].max()))
        if not want.any():
            break
        # split axis: the one whose two half-box fits leave the smallest total error
        errs = []
        for a in range(3):
            low = (x[:, a] < 0.5).astype(np.float64)
            e = np.zeros(K)
            for w in (low, 1.0 - low):
                _, r = _fit(x, sf, w, sg, K)
                e += _group_mean(r, sg, K, w)
            errs.append(e)
        best = np.argmin(np.stack(errs, 1), axis=1)
        # children of split node k get active indices 2·rank(k) and 2·rank(k) + 1
        rank = np.cumsum(want) - 1
        n_split, a = int(want.sum()), best[want]
        parents, l0, h0 = ids[want], lo[want], hi[want]
        rows = np.arange(n_split)
        mid = 0.5 * (l0[rows, a] + h0[rows, a])
        first = len(axis) + 2 * rows
        axis[parents], split[parents], child[parents] = a, mid, first
        axis = np.r_[axis, np.full(2 * n_split, -1)]
        split = np.r_[split, np.zeros(2 * n_split)]
        child = np.r_[child, np.full(2 * n_split, -1)]
        leaf = np.r_[leaf, np.full(2 * n_split, -1)]
        h_left, l_right = h0.copy(), l0.copy()
        h_left[rows, a] = mid
        l_right[rows, a] = mid
        new_ids = np.stack([first, first + 1], 1).ravel()
        new_lo = np.stack([l0, l_right], 1).reshape(-1, 3)
        new_hi = np.stack([h_left, h0], 1).reshape(-1, 3)
        keep = want[sg]
        side = x[np.arange(len(x)), best[sg]] >= 0.5
        su, sf, sg = su[keep], sf[keep], (2 * rank[sg] + side)[keep]
        ids, lo, hi = new_ids, new_lo, new_hi
        depth = np.repeat(depth[want] + 1, 2)
        counts = np.full(len(ids), samples_per_node)
    leaf_lo, leaf_hi, leaf_c = np.array(leaf_lo), np.array(leaf_hi), np.array(leaf_c)
    leaf_c = blend_interval_mean(leaf_lo, leaf_hi, leaf_c, breaks, interval_share)
    stats = GuideStats("kdtree", max_depth=deepest, evaluations=evaluations, intervals=len(breaks) - 1)
    guide = KdTreeGuide(leaf_lo, leaf_hi, leaf_c, epsilon, stats, axis, split, child, leaf)
    stats.memory_bytes = guide.memory_bytes()
    stats.build_seconds = time.perf_counter() - t0
    return guide
