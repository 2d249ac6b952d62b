"""Mesh geometry: the welded edge table, intersection curves, edge chains, remeshing, UV atlases, θ and
the smooth-shading check."""
