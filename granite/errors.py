"""Exception hierarchy. Every error a user can cause derives from :class:`GraniteError`;
the command-line tools print it as one line and exit with status 2."""

from __future__ import annotations

from pathlib import Path


class GraniteError(Exception):
    """Base class of all errors caused by user input or configuration."""


class InputError(GraniteError):
    """Bad input data: a missing or malformed file, bad values, inconsistent timestamps.

    ``str(error)`` reads ``"<path>:<line>: <message>"`` (path and line only when known), so
    the user sees which file and which line to fix.
    """

    def __init__(self, message: str, path: str | Path | None = None, line: int | None = None):
        self.message = message
        self.path = None if path is None else Path(path)
        self.line = line
        super().__init__(str(self))

    def __str__(self) -> str:
        where = ""
        if self.path is not None:
            where = f"{self.path}:{self.line}: " if self.line is not None else f"{self.path}: "
        return f"{where}{self.message}"


class ConfigError(GraniteError):
    """A configuration or scenario file with an unknown key or a value out of range."""
