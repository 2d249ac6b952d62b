"""Edge sorting (paper §4.3, Algorithm 2): order the boundary edges into long chains.

The boundary sampler maps u1 through the CDF of edge lengths, so consecutive edges of the list
are neighbours in u1. When consecutive edges share an end point and are oriented head to tail,
x^B(u1) is continuous across them and a guide over u1 sees a smooth target instead of a jump at
every edge. Chains are built greedily over welded vertices:

    start at the first unused edge (v0, v1);
    while v_cur has an unused edge (v_cur, v_next) whose direction d makes
          d · d_prev ≥ cos(max_turn) and the chain is shorter than max_length:
        take the one with the largest d · d_prev, append it, move on;
    then extend the start of the chain backwards the same way.

Algorithm 2 extends forwards only; extending both ways gives fewer, longer chains at no cost.
The result is a permutation of the edges, a per-edge ``flip`` (traverse v1 → v0) and the index
of each chain's first edge.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Chains:
    """Edge order after sorting: ``order[i]`` is the original index of the i-th edge, ``flip[i]``
    whether it is traversed from v1 to v0, ``starts`` the positions where chains begin."""
    order: np.ndarray
    flip: np.ndarray
    starts: np.ndarray

    @property
    def count(self) -> int:
        return len(self.starts)

    def mean_length(self) -> float:
        return len(self.order) / max(self.count, 1)

    @staticmethod
    def unsorted(n: int) -> "Chains":
        """Every edge its own chain, in the original order."""
        return Chains(np.arange(n), np.zeros(n, bool), np.arange(n))


@dataclass
class EdgeGraph:
    """What the greedy walks share: welded vertex positions ``P``, the edges (a[i], b[i]), the
    edges incident to each vertex, which edges a chain has taken (``used``, updated by the
    walks) and the cosine of the largest turn a chain may take."""
    P: np.ndarray
    a: np.ndarray
    b: np.ndarray
    incident: list
    used: np.ndarray
    cos_turn: float


def _extend(graph: EdgeGraph, start_vertex, prev_dir, limit: int):
    """Greedy walk from ``start_vertex``; returns [(edge, forward?)] in walking order."""
    P, a, b, incident, used, cos_turn = graph.P, graph.a, graph.b, graph.incident, graph.used, graph.cos_turn
    out, cur, d_prev = [], start_vertex, prev_dir
    while len(out) < limit:
        best, best_cos, best_fwd = -1, cos_turn, True
        for e in incident[cur]:
            if used[e]:
                continue
            fwd = a[e] == cur
            nxt = b[e] if fwd else a[e]
            d = P[nxt] - P[cur]
            n = np.linalg.norm(d)
            c = float(d @ d_prev) / n if n > 0 else -1.0
            if c >= best_cos:
                best, best_cos, best_fwd = e, c, fwd
        if best < 0:
            break
        used[best] = True
        out.append((best, best_fwd))
        nxt = b[best] if best_fwd else a[best]
        d_prev = (P[nxt] - P[cur]) / max(np.linalg.norm(P[nxt] - P[cur]), 1e-30)
        cur = nxt
    return out


def sort_edges(P, a, b, max_turn_deg: float = 60.0, max_length: int = 1024) -> Chains:
    """Chains over edges (a[i], b[i]) of welded vertex ids with positions ``P``."""
    P = np.asarray(P, float)
    a, b = np.asarray(a), np.asarray(b)
    n = len(a)
    incident = [[] for _ in range(len(P))]
    for e in range(n):
        incident[a[e]].append(e)
        incident[b[e]].append(e)
    used = np.zeros(n, bool)
    graph = EdgeGraph(P, a, b, incident, used, float(np.cos(np.radians(max_turn_deg))))
    order, flip, starts = [], [], []
    for e0 in range(n):
        if used[e0]:
            continue
        used[e0] = True
        d = P[b[e0]] - P[a[e0]]
        d = d / max(np.linalg.norm(d), 1e-30)
        ahead = _extend(graph, b[e0], d, max_length - 1)
        behind = _extend(graph, a[e0], -d, max_length - 1 - len(ahead))
        # walking backwards from a[e0] visits edges in reverse chain order and direction
        chain = [(e, not fwd) for e, fwd in reversed(behind)] + [(e0, True)] + ahead
        starts.append(len(order))
        for e, fwd in chain:
            order.append(e)
            flip.append(not fwd)
    return Chains(np.asarray(order, np.int64), np.asarray(flip, bool), np.asarray(starts, np.int64))
