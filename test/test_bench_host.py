"""bench/host.py: the host-noise benchmark writes its section, and counts a cut burst."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np

_BENCH = Path(__file__).resolve().parents[1] / "bench"
if str(_BENCH) not in sys.path:
    sys.path.insert(0, str(_BENCH))
host = importlib.import_module("host")


def test_a_burst_that_waited_beyond_its_cpu_time_counts_as_cut() -> None:
    row = host.Row("x", wall_ms=np.array([1.0, 2.6, 4.0, 4.4]),
                   cpu_ms=np.array([1.0, 2.0, 2.0, 4.0]), steal_ms=12.0)
    line = host.render([row], 1.0, 0).splitlines()[-1]
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[0] == "x" and cells[1] == "4"
    assert cells[5] == "50.00 %"  # 2.6 > 2.0 + 0.5 and 4.0 > 2.0 + 0.5; 4.4 < 4.0 + 0.5
    assert cells[4].endswith("/ 4.40") and cells[6] == "12"


def test_the_section_is_written_with_a_row_per_measurement(tmp_path: Path) -> None:
    results = tmp_path / "RESULTS.md"
    results.write_text("# Benchmark results\n\n## Other\n\nkept\n")
    assert host.main(["--seconds", "0.2", "--busy", "1", "--results", str(results)]) == 0
    text = results.read_text()
    assert "## Other\n\nkept" in text
    section = text[text.index(host.SECTION):]
    rows = [line for line in section.splitlines() if line.startswith("| ") and "---" not in line]
    assert len(rows) == 1 + 1 + len(host.BURSTS_MS)  # header, fixed work, each burst length
    for line in rows[1:]:
        cpu = [float(x) for x in line.split("|")[3].split("/")]
        assert 0.0 < cpu[0] <= cpu[1] <= cpu[2] <= cpu[3]
    for line, ms in zip(rows[2:], host.BURSTS_MS, strict=True):
        assert float(line.split("|")[3].split("/")[0]) >= ms  # spun at least its CPU time
