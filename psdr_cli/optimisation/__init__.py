"""The optimisation loop's parts: its differentiable state, one iteration, the recorded iteration, the
schedule, the engines, the views' pose corrections, the unknown light and the run's starting state."""
