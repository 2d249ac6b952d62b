"""The losses an optimisation minimises, one per module: :mod:`.l1` (the photometric L1 of a
render against its target) and :mod:`.silhouette` (the L1 of the rendered coverage against a
photograph's mask)."""
