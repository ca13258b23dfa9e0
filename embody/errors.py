"""One error hierarchy, so the CLI can map failures to its exit codes (2 = bad input/config)."""

from __future__ import annotations


class EmbodyError(Exception):
    """Base class of every error embody raises on purpose."""


class InputError(EmbodyError):
    """A bad input file: names the file and the offending field in one line."""

    def __init__(self, path: object, field: str | None, message: str) -> None:
        self.path = str(path)
        self.field = field
        self.message = message
        where = f"{self.path}" + (f": field '{field}'" if field else "")
        super().__init__(f"{where}: {message}")


class ConfigError(EmbodyError):
    """A bad configuration value: names the dotted key."""

    def __init__(self, key: str, message: str) -> None:
        self.key = key
        self.message = message
        super().__init__(f"config '{key}': {message}")


class UsageError(EmbodyError):
    """A bad command-line usage that click itself cannot detect."""
