"""One error type for bad input data, so callers can tell it from bugs."""

from __future__ import annotations


class DataError(ValueError):
    """Bad or unreadable input; the message names the file, the demo and the key where known."""

    def __init__(self, file, problem: str, demo: str | None = None, key: str | None = None):
        self.file, self.demo, self.key, self.problem = str(file), demo, key, problem
        where = [self.file] + ([str(demo)] if demo is not None else []) + ([f"key {key!r}"] if key else [])
        super().__init__(f"{': '.join(where)}: {problem}")


class CollectionError(LookupError):
    """A collection or key that the store does not hold; the message lists what it does hold."""
