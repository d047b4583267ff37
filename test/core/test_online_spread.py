"""The first correction of a long loop: spread along its chain inside the budget."""

from __future__ import annotations

import time
from collections import Counter

import pytest
from graphs import loop_graph

from h2o_slam.core.converge import Solution, merge_solution
from h2o_slam.core.graph import EdgeKind, PoseGraph
from h2o_slam.core.modes import add_arrival, arrivals, solve_exact
from h2o_slam.core.online import OnlineConfig, OnlineH2O, StepReport, _chi2_of


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
def test_a_loop_that_older_closures_cross_is_solved(planar: bool) -> None:
    """Closures inside the loop and across its start tie the poses the spread moves as if
    nothing did: the loop solve takes them in."""
    g = loop_graph(3, planar, 300, reverse=True, closures=((150, 40), (260, 120)))
    solved, counts = chi2_after_closure(g, True, True, None)
    assert counts == {"solved": 3}
    assert solved < 1.01


def test_a_queued_closure_far_off_is_updated_before_a_waiting_solution_is_merged() -> None:
    """A solution older than a new closure far off waits for the closure's update (which
    then marks it stale): merged first, it took the callback's time from that update."""
    g = loop_graph(4, True, 120, reverse=False)
    h2o = OnlineH2O(planar=True, online=OnlineConfig(background="inline", spread_loops=False))
    try:
        older, closure = _older_solution_then_closure(h2o, g)
        conv = h2o.converger
        conv._merging, conv._cursor = older, 0  # noqa: SLF001 - a solution waiting
        assert h2o._big_closure_queued()  # noqa: SLF001
        merges, dropped = conv.state.merges, conv.state.dropped
        h2o.step(0.5)
        assert _chi2_of(h2o.solver, closure) < 10.0 and conv.state.merges == merges
        h2o.step(0.5)
        assert conv.state.dropped == dropped + 1  # stale: never merged
    finally:
        h2o.close()


def test_a_merge_under_way_waits_out_the_step_that_corrects_a_big_closure() -> None:
    """A solution without the closure, half merged when the closure arrives: the step that
    corrects the closure does not finish that merge (the map keeps the correction); the next
    finishes it and corrects the closure again."""
    g = loop_graph(4, True, 120, reverse=False)
    h2o = OnlineH2O(planar=True, online=OnlineConfig(background="inline", spread_loops=False))
    try:
        older, closure = _older_solution_then_closure(h2o, g)
        conv = h2o.converger
        half = older.nodes // 2
        conv._merging = older  # noqa: SLF001 - a merge under way: half of it staged
        conv._staged_for(older).stage(h2o.solver.tree.parent, 0, half)  # noqa: SLF001
        conv._cursor = half  # noqa: SLF001
        h2o._corrected = 0  # noqa: SLF001 - what a step starts with
        raw = _chi2_of(h2o.solver, closure)
        h2o._relax_new(float("inf"), StepReport())  # noqa: SLF001 - the closure's update
        corrected = h2o.solver.chi2(g)
        assert _chi2_of(h2o.solver, closure) < 0.1 * raw
        # The rest of that step: its last chance to merge.
        h2o._converge_within(time.perf_counter() + 1.0, False, True, StepReport())  # noqa: SLF001
        assert conv._merging is older  # noqa: SLF001 - held
        assert h2o.solver.chi2(g) == corrected
        merges = conv.state.merges
        h2o.step(0.5)
        assert conv._merging is None and conv.state.merges > merges  # noqa: SLF001
        assert h2o.solver.chi2(g) < 1.5 * corrected
    finally:
        h2o.close()


@pytest.mark.parametrize("planar", [True, False])
def test_a_crossed_loop_is_spread_along_its_tail_not_whole(
        planar: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """Without the loop solve, the two closures that older ones cross are spread along the
    poses after the newest one they cross (measured: 1.25 and 3.3 times the optimum's χ²),
    not along the whole loop, which bends the older closures (1.5·10⁴), and not left to the
    tree path's update alone (147 and 1,805)."""
    g = loop_graph(3, planar, 300, reverse=True, closures=((150, 40), (260, 120)))
    tail, counts = chi2_after_closure(g, True, False, None)
    assert counts == {"crossed": 2, "tail": 2, "kept": 1}
    with monkeypatch.context() as patch:
        patch.setattr(OnlineH2O, "_spread_tail", lambda *args: True)
        alone, counts = chi2_after_closure(g, True, False, None)
    assert counts == {"crossed": 2, "kept": 1}
    monkeypatch.setattr(OnlineH2O, "_ties_inside", lambda *args: [])
    whole, counts = chi2_after_closure(g, True, False, None)
    assert counts == {"kept": 3}
    assert tail < 5.0
    assert tail < 0.02 * min(alone, whole)


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


def _older_solution_then_closure(h2o: OnlineH2O, g: PoseGraph) -> tuple[Solution, int]:
    """Feed all of ``g`` but its last pose, solve (the older solution), add the last pose
    and its closure; the solution and the closure's edge."""
    feed = list(arrivals(g))
    for node, edges in enumerate(feed[:-1]):
        add_arrival(h2o, g, node, edges)
        h2o.step(None)
    older = h2o.converger.solve_now(h2o._clock)  # noqa: SLF001 - solved before the closure
    assert older is not None
    add_arrival(h2o, g, len(feed) - 1, feed[-1])
    return older, h2o.solver.num_edges - 1


def test_closures_an_older_solution_undid_are_relaxed_again() -> None:
    """Without the spread, a closure's correction is its relaxation; merging a solution
    solved without the closure puts back the bent map (the closure far off again), so the
    closure is queued again, first, and the next step corrects it."""
    g = loop_graph(4, True, 120, reverse=False)
    h2o = OnlineH2O(planar=True, online=OnlineConfig(background="inline", spread_loops=False))
    try:
        older, closure = _older_solution_then_closure(h2o, g)
        h2o._relax_new(float("inf"), StepReport())  # noqa: SLF001 - the closure's update
        corrected = h2o.solver.chi2(g)
        assert closure not in h2o.pending
        merge_solution(h2o.solver.tree, older)
        undone = h2o.solver.chi2(g)
        assert undone > 10.0 * corrected
        h2o._after_merge(older)  # noqa: SLF001 - what completing that merge does
        assert list(h2o.pending)[:1] == [closure]
        h2o._relax_new(float("inf"), StepReport())  # noqa: SLF001
        assert h2o.solver.chi2(g) < 1.5 * corrected
    finally:
        h2o.close()


def test_a_solution_without_a_big_closure_is_dropped_not_merged() -> None:
    """A closure whose first correction took its χ² down from far above the map's marks
    every solution solved without it stale: one that arrives later is dropped, and the map
    keeps the correction."""
    g = loop_graph(4, True, 120, reverse=False)
    h2o = OnlineH2O(planar=True, online=OnlineConfig(background="inline", spread_loops=False))
    try:
        older, closure = _older_solution_then_closure(h2o, g)
        raw = float(h2o.solver.residual(closure) @ h2o.solver.residual(closure))
        assert raw > 100.0
        h2o._relax_new(float("inf"), StepReport())  # noqa: SLF001 - its first correction
        corrected = h2o.solver.chi2(g)
        dropped = h2o.converger.state.dropped
        h2o.converger._received(older)  # noqa: SLF001 - as if the worker returned it now
        assert h2o.converger.state.dropped == dropped + 1
        h2o.step(5e-3)
        assert h2o.solver.chi2(g) <= corrected
    finally:
        h2o.close()
