"""The first correction of a long loop: spread along its chain inside the budget."""

from __future__ import annotations

from collections import Counter

import pytest
from graphs import loop_graph

from h2o_slam.core.graph import EdgeKind, PoseGraph
from h2o_slam.core.modes import add_arrival, arrivals, solve_exact
from h2o_slam.core.online import OnlineConfig, OnlineH2O


def chi2_after_closure(g: PoseGraph, spread: bool, solve: bool, budget_s: float | None
                       ) -> tuple[float, Counter[str]]:
    """χ² right after the callback that brings the last closure of ``g``, over the optimum,
    with H₂O's updates alone (no exact solves); and the first corrections counted."""
    h2o = OnlineH2O(planar=g.planar, online=OnlineConfig(background="off", spread_loops=spread,
                                                         solve_loops=solve))
    try:
        for node, edges in enumerate(arrivals(g)):
            add_arrival(h2o, g, node, edges)
            h2o.step(budget_s)
        return h2o.solver.chi2(g) / solve_exact(g).chi2_final, h2o.spreads
    finally:
        h2o.close()


@pytest.mark.parametrize("planar", [True, False])
def test_the_first_correction_of_a_long_loop_is_near_its_optimum(planar: bool) -> None:
    # Unbudgeted, so that no machine is too slow for it: the tree path's update then
    # solves its whole domain, and still leaves the loop bent.
    g = loop_graph(3, planar, 300, reverse=True)
    solved, counts = chi2_after_closure(g, True, True, None)
    spread, kept = chi2_after_closure(g, True, False, None)
    alone, _ = chi2_after_closure(g, False, False, None)
    assert counts == {"solved": 1}
    assert kept == {"kept": 1}
    assert solved < 1.1
    assert spread < 1.1
    assert alone > 100.0 * max(spread, solved)


@pytest.mark.parametrize("planar", [True, False])
def test_a_loop_that_older_closures_cross_is_solved_not_spread(planar: bool) -> None:
    """Closures inside the loop and across its start tie the poses the spread moves as if
    nothing did: its answer bends them (thousands of times the optimum here), the loop
    solve's does not."""
    g = loop_graph(3, planar, 300, reverse=True, closures=((150, 40), (260, 120)))
    solved, counts = chi2_after_closure(g, True, True, None)
    spread, _ = chi2_after_closure(g, True, False, None)
    assert counts == {"solved": 3}
    assert solved < 1.01
    assert spread > 100.0


def test_closures_a_merged_solution_left_out_are_spread_again() -> None:
    """A solution merged after a closure arrived was solved without it: the closure's
    correction went with the poses the merge replaced, so it is queued again."""
    g = loop_graph(4, True, 120, reverse=False)
    h2o = OnlineH2O(planar=True, online=OnlineConfig(background="inline"))
    try:
        feed = list(arrivals(g))
        for node, edges in enumerate(feed[:-1]):
            add_arrival(h2o, g, node, edges)
            h2o.step(None)
        solution = h2o.converger.solve_now(h2o._clock)  # noqa: SLF001 - an older solution
        assert solution is not None
        add_arrival(h2o, g, len(feed) - 1, feed[-1])
        h2o.step(None)
        closure = h2o.solver.num_edges - 1
        assert h2o.solver.kind[closure] == EdgeKind.RELATIVE
        h2o.pending.clear()
        h2o._after_merge(solution)  # noqa: SLF001 - the merge of the older solution
        assert closure in h2o._respread  # noqa: SLF001
    finally:
        h2o.close()


def test_a_planar_loop_is_condensed_first() -> None:
    """Each of the three closures' first correction starts with the condensed solve (its
    cost model sampled once each), and the loop solve finishes from its answer."""
    g = loop_graph(3, True, 300, reverse=True, closures=((150, 40), (260, 120)))
    h2o = OnlineH2O(planar=True, online=OnlineConfig(background="off"))
    try:
        for node, edges in enumerate(arrivals(g)):
            add_arrival(h2o, g, node, edges)
            h2o.step(None)
        assert h2o.condensed_loop.cost.samples == 3
        assert h2o.spreads == {"solved": 3}
        assert h2o.solver.chi2(g) / solve_exact(g).chi2_final < 1.01
    finally:
        h2o.close()
