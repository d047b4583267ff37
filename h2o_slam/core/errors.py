"""The package's error hierarchy: one small class per kind of failure."""

from __future__ import annotations


class H2OError(Exception):
    """Base class of every error this package raises on purpose."""


class InputError(H2OError):
    """Input (a file, a message, a parameter) that cannot be used, with the reason."""


class GraphError(H2OError):
    """A pose graph that is inconsistent: unknown node ids, bad edge endpoints."""


class G2OFormatError(InputError):
    """A g2o file that cannot be read; the message names file, line and reason."""

    def __init__(self, path: str, line: int, reason: str) -> None:
        self.path = path
        self.line = line
        self.reason = reason
        super().__init__(f"{path}:{line}: {reason}")
