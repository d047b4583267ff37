"""The progress bar: drawn on a terminal only."""

from __future__ import annotations

import io

from h2o_slam.app.progress import Progress


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_draws_only_on_a_terminal() -> None:
    quiet = io.StringIO()
    bar = Progress(10.0, "replay", stream=quiet)
    bar.update(5.0)
    bar.close()
    assert quiet.getvalue() == ""
    tty = _Tty()
    bar = Progress(10.0, "replay", stream=tty, min_interval_s=0.0)
    bar.update(5.0, note="3 GPS")
    bar.update(10.0)
    bar.close()
    lines = tty.getvalue().split("\r")
    assert "replay [" in lines[1] and " 50% 5.0/10.0 s" in lines[1] and "3 GPS" in lines[1]
    assert "100%" in lines[-1] and lines[-1].endswith("\n") and "x real time" in lines[-1]
