"""The estimate of dI/dθ and rendering: what ``psdr grad``, ``psdr compare`` and the loop share, the renderer,
finite differences, a moving camera's needs, and psdr as a Mitsuba integrator and plugin."""
