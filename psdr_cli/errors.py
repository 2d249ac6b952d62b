"""Errors the user can act on. The CLI prints them as one line and exits non-zero."""
from __future__ import annotations


class PsdrError(Exception):
    """A problem with the user's input or environment, described in one line."""


class ConfigError(PsdrError):
    """A bad value in an experiment file: ``<file>: <key path>: <what was expected>``."""

    def __init__(self, file, key: str, message: str):
        self.file, self.key, self.message = str(file), key, message
        where = f"{self.file}: {key}" if key else self.file
        super().__init__(f"{where}: {message}")


class PsdrWarning(UserWarning):
    """Something psdr recovered from (e.g. a damaged log.csv tail); the CLI prints it as one line."""
