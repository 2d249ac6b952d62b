"""Guided boundary sampling (paper §4): guides over u ∈ [0,1)³ and their targets (edge sorting,
which orders the edges the guides see, is :mod:`psdr_cli.geometry.edge_sort`)."""
from .grid import GridGuide, build_grid
from .guide import Guide, GuideStats
from .kdtree import KdTreeGuide, build_kdtree

__all__ = ["Guide", "GuideStats", "GridGuide", "KdTreeGuide", "build_grid", "build_kdtree"]
