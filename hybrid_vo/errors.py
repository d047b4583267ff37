"""The hybrid odometer's error classes: one small class per kind of failure.

Both derive from :class:`ValueError` as well, so callers that only know "a bad value" can
catch that.
"""

from __future__ import annotations


class HybridVOError(Exception):
    """Base class of every error this package raises on purpose."""


class ConfigError(HybridVOError, ValueError):
    """A configuration, calibration or mounting value that cannot be used, with the reason."""


class FrameError(HybridVOError, ValueError):
    """An input frame or wheel increment that cannot be used (shape, dtype, NaN), with why."""
