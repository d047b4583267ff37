"""Freed memory kept for reuse: a callback's arrays land on resident pages."""

from __future__ import annotations

import resource

import numpy as np
import pytest

from h2o_slam.core import heap


def _faults_of_allocations(mb: int, times: int) -> int:
    """Minor page faults of allocating, writing and freeing ``mb`` MB ``times`` times."""
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(times):
        block = np.empty(mb << 17)
        block[:] = 1.0
        del block
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


def test_arrays_allocated_after_the_reserve_reuse_resident_pages() -> None:
    if not heap.keep_freed_memory(16):
        pytest.skip("the C library has no mallopt")
    # 4 MB a time, freed in between: each would be a fresh mmap (1,024 faults) otherwise.
    assert _faults_of_allocations(4, 10) < 200


def test_a_negative_reserve_is_refused() -> None:
    with pytest.raises(ValueError, match="reserve_mb"):
        heap.keep_freed_memory(-1)
