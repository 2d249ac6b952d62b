"""``python -m psdr_cli`` runs the CLI."""
from .cli import run

run()
