"""The subcommands, one module each (``psdr grad``, ``compare``, ``optimize``, ``evaluate``, ``export``, the sweeps
behind ``--ray``, ``relight``): what ``api.py`` delegates to."""
