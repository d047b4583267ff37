"""The boundary every callback of a node runs behind: no exception reaches the executor.

rclpy lets an exception raised in a subscription, timer or service callback out of
``spin``, which ends the node. Both nodes therefore wrap every callback they register; the
node decides how to log and count what was caught (issue 13: one message must never cost
the node or the map).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


def behind_boundary(what: str, work: Callable[..., Any],
                    on_error: Callable[[str, Exception], None]) -> Callable[..., Any]:
    """``work`` wrapped so that an exception goes to ``on_error(what, exc)`` instead of the
    caller. A service callback (``(request, response)`` with a ``success`` field) then
    answers ``success=False`` naming the error; any other callback returns ``None``.
    ``BaseException`` (``KeyboardInterrupt``, ``SystemExit``) still passes: it stops the
    process on purpose."""

    def run(*args: Any) -> Any:
        try:
            return work(*args)
        except Exception as exc:  # the boundary itself
            on_error(what, exc)
            if len(args) == 2 and hasattr(args[1], "success"):
                response = args[1]
                response.success = False
                response.message = f"{what} failed: {type(exc).__name__}: {exc}"[:500]
                return response
            return None

    return run
