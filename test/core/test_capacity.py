"""Arrays grown by doubling, and ahead of need in a step's spare time."""

from __future__ import annotations

import numpy as np
import pytest

from h2o_slam.core.capacity import Growable, GrowAhead, ensure
from h2o_slam.core.modes import add_arrival, arrivals
from h2o_slam.core.online import OnlineConfig, OnlineH2O
from h2o_slam.io.synthetic import manhattan


class _Owner:
    def __init__(self) -> None:
        self.full = np.arange(8.0)
        self.half = np.arange(8.0)
        self.blocks = np.tile(np.eye(3), (8, 1, 1))


def test_arrays_three_quarters_full_double_and_keep_their_rows() -> None:
    owner = _Owner()
    ahead = GrowAhead()
    arrays = [Growable(owner, "full", -1.0, 6), Growable(owner, "half", -1.0, 4),
              Growable(owner, "blocks", np.eye(3), 7)]
    assert ahead.run(arrays, 17, deadline=1.0, clock=lambda: 0.0)
    np.testing.assert_array_equal(owner.full, [*range(8), *[-1.0] * 8])
    np.testing.assert_array_equal(owner.half, np.arange(8.0))  # half full: left alone
    assert owner.blocks.shape == (16, 3, 3)
    np.testing.assert_array_equal(owner.blocks, np.tile(np.eye(3), (16, 1, 1)))
    assert ahead.grown == 2


def test_an_array_whose_copy_would_pass_the_deadline_waits() -> None:
    owner = _Owner()
    ahead = GrowAhead()
    before = owner.full
    # 128 bytes at 1 ns each, twice over, does not fit in 100 ns.
    assert not ahead.run([Growable(owner, "full", 0.0, 8)], 8, deadline=1e-7,
                         clock=lambda: 0.0)
    assert owner.full is before
    assert ahead.due(8)  # tried again at the next step


def test_an_empty_array_grows_too() -> None:
    owner = _Owner()
    owner.full = np.zeros((0, 3))
    ahead = GrowAhead()
    assert ahead.run([Growable(owner, "full", 0.0, 0)], 0, deadline=1.0, clock=lambda: 0.0)
    assert owner.full.shape == (1, 3)


def test_the_arrays_are_looked_at_again_only_when_one_may_be_three_quarters_full() -> None:
    owner = _Owner()
    ahead = GrowAhead()
    assert ahead.due(0)
    # 'half' (8 rows, 4 in use) is three quarters full at 6 rows: 2 more; 'full' grows to 16
    # rows with 6 in use, three quarters full at 12: 6 more.
    ahead.run([Growable(owner, "full", 0.0, 6), Growable(owner, "half", 0.0, 4)], 10,
              deadline=1.0, clock=lambda: 0.0)
    assert not ahead.due(11) and ahead.due(12)


def test_owners_arrays_of_different_capacities_all_get_room() -> None:
    """One array grown ahead, the others not: an append past the old end finds room in
    every array, the grown one left as it is."""
    owner = _Owner()
    ahead_grown = np.concatenate([owner.half, np.zeros(24)])
    owner.half = ahead_grown
    ensure([(owner, "full", 0.0), (owner, "half", 0.0)], 9)
    assert len(owner.full) == 16 and owner.half is ahead_grown


def _stream(graph, grow_ahead: bool) -> tuple[OnlineH2O, int]:
    """Feed ``graph`` pose by pose with budgeted steps on a clock that never advances (every
    update fits); count the arrays an arrival had to grow itself."""
    h2o = OnlineH2O(planar=graph.planar, online=OnlineConfig(freeze_gc=False,
                                                             background="off"))
    h2o._clock = lambda: 0.0
    if not grow_ahead:
        h2o._grow_ahead.run = lambda *args: True  # type: ignore[method-assign]
    forced = 0
    for node, edges in enumerate(arrivals(graph)):
        before = [id(getattr(owner, name)) for owner, name, _ in _all(h2o)]
        add_arrival(h2o, graph, node, edges)
        after = [id(getattr(owner, name)) for owner, name, _ in _all(h2o)]
        forced += sum(x != y for x, y in zip(before, after, strict=True))
        h2o.step(5e-3)
    return h2o, forced


def _all(h2o: OnlineH2O) -> list[tuple[object, str, object]]:
    return [(g.owner, g.name, g.fill) for g in h2o._growables()]


@pytest.mark.parametrize("seed", [1, 2])
def test_budgeted_steps_grow_the_arrays_before_an_arrival_needs_it(seed: int) -> None:
    """With spare time in every step no arrival grows an array itself, and the map is the
    one grown on demand, to the last bit."""
    graph = manhattan(300, seed=seed).graph
    ahead, forced_ahead = _stream(graph, grow_ahead=True)
    demand, forced_demand = _stream(graph, grow_ahead=False)
    assert forced_demand > 0  # the stream does outgrow the first capacities
    assert forced_ahead == 0
    assert ahead._grow_ahead.grown >= forced_demand
    R_a, t_a = ahead.solver.world_poses()
    R_d, t_d = demand.solver.world_poses()
    np.testing.assert_array_equal(t_a, t_d)
    np.testing.assert_array_equal(R_a, R_d)
    np.testing.assert_array_equal(ahead.solver.B[: ahead.solver.num_nodes],
                                  demand.solver.B[: demand.solver.num_nodes])
