"""The losses an optimisation minimises, one per module, each declaring its ``LOSS``
(:class:`.loss.Loss`): :mod:`.l1` (the photometric L1 of a render against its target) and
:mod:`.silhouette` (the L1 of the rendered coverage against a photograph's mask). :mod:`.registry`
lists them; adding a loss is its module plus its name there."""
