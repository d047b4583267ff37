"""The one error class of :mod:`msg_adapters`."""

from __future__ import annotations

from h2o_slam.core.errors import InputError


class AdapterError(InputError, ValueError):
    """A message that cannot be used; the text names the field and the problem.

    A :class:`h2o_slam.core.errors.InputError` (so a node can count every rejected input alike)
    and a :class:`ValueError` (so callers that know nothing of this package can still
    catch it). Nodes log the text, count the message as rejected and skip it
    (doc/nodes.md, bad input).
    """
