"""``python -m psdr_cli`` runs the CLI."""
import sys

from .cli import run

sys.exit(run())
