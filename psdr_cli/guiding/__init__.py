"""Guided boundary sampling (paper §4): guides over u ∈ [0,1)³, their targets, edge sorting."""
from .grid import GridGuide, build_grid
from .guide import Guide, GuideStats
from .kdtree import KdTreeGuide, build_kdtree

__all__ = ["Guide", "GuideStats", "GridGuide", "KdTreeGuide", "build_grid", "build_kdtree"]
