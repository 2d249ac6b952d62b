"""The unknowns of an optimisation, one per module, each declaring its ``UNKNOWN``
(:class:`.unknown.Unknown`): :mod:`.shape` (the large-steps shape), :mod:`.albedo` (a colour or a
texture), :mod:`.environment_rotation`, :mod:`.environment_map`, :mod:`.materials` and
:mod:`.cameras` (the views' pose corrections). :mod:`.registry` lists them; adding an unknown is
its module plus its name there."""
