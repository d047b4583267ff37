"""Outlier-robust exact solves: graduated non-convexity with a truncated quadratic.

Loop closures from place recognition and GPS fixes are sometimes wrong yet well formed (two
similar corridors, a multipath jump); odometry is trusted. Every untrusted edge carries a
weight ``w ∈ [0, 1]`` on its information, chosen by Graduated Non-Convexity with the
truncated least squares (TLS) cost of Yang, Antonante, Tzoumas & Carlone, "Graduated
non-convexity for robust spatial perception: from non-minimal solvers to global outlier
rejection" (RA-L 2020):

* the TLS cost of an edge with squared Mahalanobis residual ``r²`` is ``min(r², c̄²)``: an
  edge further than ``c̄²`` from the map costs the same however far, so it cannot bend it;
* GNC minimizes a surrogate ``ρ_μ`` that is convex for small ``μ`` (least squares) and the
  TLS cost as ``μ → ∞``, alternating a weighted Gauss–Newton solve with the closed-form
  weight of eq. (14) of the paper (:func:`tls_weights`), ``μ₀ = c̄² / (2 r²_max − c̄²)``
  and ``μ ← 1.4 μ``;
* ``c̄²`` is the χ² quantile :attr:`RobustConfig.inlier_probability` of the edge's degrees
  of freedom, so on a graph without outliers (every residual at the optimum below it: true
  of every public graph this package is benchmarked on) the answer is the least-squares
  optimum itself.

GNC ends in a local minimum of the TLS cost; local moves that must lower it follow
(re-admission by place, drops of single closures and of places: :func:`_settle`), and a
place whose closures are jointly incompatible with the map built without them is dropped
whatever the TLS cost says (Neira & Tardós's joint compatibility test,
:func:`_incompatible_place`): a weakly tied map can bend to fit a group of consistent
false closures for less than the cost of leaving them out. The final decisions are then
solved by least squares once more from a start that does not depend on the path the
decisions took (LAGO of the kept edges on planar graphs, the chordal initialization in
3-D), and that answer is kept where its χ² is lower (:func:`restarted_if_lower`).

The scores these moves weigh (each closure's deletion χ², a place's joint one, the
innovation of a closure that is out) read blocks of the map's covariance ``H⁻¹`` at the
closures' ends: from the selected inverse (:mod:`h2o_slam.core.selinv`) when many are
scored, from columns of ``H⁻¹`` when a few are, and by one solve with the group left out
for a place of many closures (:func:`_group_chi2`). Where only a few drop candidates are
weighed, the edges around each bound its deletion χ² first
(:mod:`h2o_slam.core.neighbourhood`), and only those the bound does not clear are scored.

The weights end binary; :func:`edge_states` names them for reports and diagnostics
(:class:`EdgeState`). Weights live in the solver's edge table
(:meth:`~h2o_slam.core.solver.H2OSolver.set_weights`), so every solver path (exact, the
single-edge updates, the background solves) uses the same ones.
"""

from __future__ import annotations

import hashlib
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import scipy.sparse as sp

from h2o_slam.core import geometry as geo
from h2o_slam.core.exact import ExactSystem, converge_exact, settled
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import (
    EdgeKind,
    PoseGraph,
    edge_chi2,
    has_global,
    odometry_chain,
)
from h2o_slam.core.neighbourhood import Neighbourhoods, whitened_terms
from h2o_slam.core.selinv import SelectedInverse, selected_inverse
from h2o_slam.core.solver import H2OSolver
from h2o_slam.core.spd import SPDFactor, positions, upper, with_entries

#: ``restart(weights) -> (R, t)``: a start for the solve with these edge weights.
Restart = Callable[[Array], tuple[Array, Array]]
#: ``split(B) -> (Y, Z)`` with ``Yᵀ Z = Bᵀ H⁻¹ B`` (:meth:`SPDFactor.split_solve`).
Split = Callable[[Array], tuple[Array, Array]]



def chdtri(dof: Array | float, tail: float) -> Array:
    """The χ² quantile with upper tail ``tail``. scipy.special on first use: imported with
    the module it (and scipy.stats even more) cost every command 0.05-0.7 s of start."""
    from scipy.special import chdtri as quantile

    return np.asarray(quantile(dof, tail), dtype=float)


class EdgeState(IntEnum):
    """What the robust back end decided about an edge."""

    TRUSTED = 0  #: odometry: always in, weight 1
    ACCEPTED = 1  #: weight 1
    DOWNWEIGHTED = 2  #: 0 < weight < 1 (while the graduation runs)
    DROPPED = 3  #: weight 0: the edge does not move the map


#: Weights at least this close to 1 (0) count as accepted (dropped).
WEIGHT_TOLERANCE = 1e-3


@dataclass(frozen=True)
class RobustConfig:
    """Settings of the GNC-TLS solve.

    Attributes:
        inlier_probability: ``c̄²`` is this quantile of χ² with the edge's degrees of
            freedom (3 for planar relative edges, 6 in 3-D, 2 or 3 for GPS positions):
            30.7 for a planar closure. At 0.999 (16.3) manhattan's true closures, up to 14
            at the optimum, sit so near it that 9–17 of them stayed out beside planted
            outliers (0.1 m off the outlier-free map); at 0.99999 (25.9) two weakly tied
            ones, with innovations of 26.0 and 29.6, did (χ² of the true edges 3.4× the
            optimum); a false closure of the benchmark's kind is hundreds to thousands.
        mu_factor: growth of ``μ`` per graduation step (1.4 in the paper).
        max_steps: most graduation steps; the weights are rounded to 0/1 after them.
        inner_iterations: Gauss–Newton iterations per graduation step (warm started).
        noise_margin: loop closures' ``c̄²`` is scaled by ``min(1, noise_margin · s)``, ``s``
            the closures' real noise as a share of their stated covariance
            (:func:`closure_noise_scale`): the thresholds tighten only where the stated
            covariance overstates the noise by more than this factor (variance). Measured
            ``s``: 0.027-16 on the planar public graphs and sphere2500, 4.8e-5 on
            parking-garage, whose information is the identity while its edges fit to
            ``χ² ≤ 0.017``; there, at the unscaled ``c̄²`` = 38, bending the map onto a false
            closure costs less than leaving it out.
        tail_factor: with enough accepted loop closures, their ``c̄²`` is at most this
            many times the 99th percentile of their χ² (:func:`tail_thresholds`); ``inf``
            turns the cap off.
    """

    inlier_probability: float = 0.999999
    mu_factor: float = 1.4
    max_steps: int = 200
    inner_iterations: int = 3
    noise_margin: float = 100.0
    tail_factor: float = 30.0

    def __post_init__(self) -> None:
        if not 0.0 < self.inlier_probability < 1.0:
            raise ValueError("inlier_probability must be in (0, 1)")
        if not self.mu_factor > 1.0:
            raise ValueError("mu_factor must be > 1")
        if self.max_steps < 1 or self.inner_iterations < 1:
            raise ValueError("max_steps and inner_iterations must be at least 1")
        if not self.noise_margin > 0.0:
            raise ValueError("noise_margin must be > 0")
        if not self.tail_factor > 0.0:
            raise ValueError("tail_factor must be > 0")


@dataclass
class RobustOutcome:
    """What :func:`converge_robust` did.

    Attributes:
        weights: final weight of every edge.
        history: χ² (weighted) after each Gauss–Newton iteration, the start first.
        steps: graduation steps run (0: every residual was below its threshold at the
            least-squares optimum, which is then the answer).
        converged: the final weighted solve converged.
    """

    weights: Array
    history: list[float]
    steps: int
    converged: bool


def lago_restart(graph: PoseGraph) -> Restart:
    """LAGO (Carlone et al.) of the planar ``graph``'s relative edges, each edge's
    information scaled by a weight (0: left out): the robust solve's cold start for a set of
    decisions, with no initial guess and so no local minimum of its own to fall into."""
    from h2o_slam.core.lago import lago

    def start(weights: Array) -> tuple[Array, Array]:
        keep = (weights > 0.0) & (graph.kind == EdgeKind.RELATIVE)
        sub = PoseGraph(graph.planar, graph.ids, graph.R, graph.t, graph.kind[keep],
                        graph.a[keep], graph.b[keep], graph.meas_R[keep], graph.meas_t[keep],
                        graph.info[keep] * weights[keep][:, None, None])
        result = lago(sub, ignore_global=True)
        return result.R, result.t

    return start


def chordal_restart(graph: PoseGraph) -> Restart:
    """The chordal initialization (:mod:`h2o_slam.core.chordal`) of the 3-D ``graph``'s
    relative edges, each weighted (0: left out): the 3-D sibling of :func:`lago_restart`."""
    from h2o_slam.core.chordal import chordal

    def start(weights: Array) -> tuple[Array, Array]:
        return chordal(graph, weights)

    return start


def global_restart(graph: PoseGraph) -> Restart | None:
    """The start that needs no guess for ``graph``'s kind: LAGO of a planar graph, the
    chordal initialization of a 3-D one; none for a 3-D graph with GPS or compass edges
    (the chordal relaxation leaves them out, and the map they anchor with them)."""
    if graph.planar:
        return lago_restart(graph)
    return None if has_global(graph) else chordal_restart(graph)


def odometry_edges(kind: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Relative edges between consecutive poses: the odometry chain of a g2o graph and of
    :class:`~h2o_slam.ros.mapper.Mapper`'s keyframes (trusted by the robust solve)."""
    return (kind == EdgeKind.RELATIVE) & (np.abs(b - a) == 1)


def thresholds(kind: np.ndarray, planar: bool, probability: float) -> Array:
    """``c̄²`` of each edge: the χ² quantile of its degrees of freedom."""
    rel = 3 if planar else 6
    gps = 2 if planar else 3
    dof = np.where(kind == EdgeKind.RELATIVE, rel, np.where(kind == EdgeKind.POSITION, gps, 3))
    return np.asarray(chdtri(dof, 1.0 - probability), dtype=float)


def edge_thresholds(graph: PoseGraph, trusted: np.ndarray, config: RobustConfig) -> Array:
    """``c̄²`` of each of ``graph``'s edges: :func:`thresholds`, the loop closures' scaled by
    ``min(1, noise_margin · s)`` (:attr:`RobustConfig.noise_margin`,
    :func:`closure_noise_scale`). GPS fixes keep theirs: their noise is another sensor's."""
    c2 = thresholds(graph.kind, graph.planar, config.inlier_probability)
    scale = min(1.0, config.noise_margin * closure_noise_scale(graph, trusted))
    return np.where(graph.kind == EdgeKind.RELATIVE, c2 * scale, c2)


def tail_thresholds(r2: Array, closures: np.ndarray, accepted: np.ndarray, c2: Array,
                    factor: float) -> Array:
    """``c̄²`` with the loop closures' capped at ``factor`` (:attr:`RobustConfig.tail_factor`)
    times the
    :data:`TAIL_QUANTILE` quantile of the ``accepted`` closures' squared residuals ``r2``
    at a map of the decisions, when there are at least :data:`TAIL_MIN_CLOSURES` of them:
    the thresholds as wide as the closures' own tail needs.

    :func:`edge_thresholds` scales ``c̄²`` by the closures' median noise with a wide margin,
    because real noise has heavy tails: parking-garage's true closures reach a deletion χ²
    of 11 times their median-scaled ``c̄²`` at the optimum. On city10000 (Gaussian noise,
    its stated covariance 22 times the real one) that margin let 2 of 1,000 local false
    closures in, at innovations of 8 and 15 times it, where no true closure is above 0.27.
    The accepted closures' tail tells the two apart: 30 times its 99th percentile is 2.5
    times city10000's median-scaled ``c̄²`` and 37 times parking-garage's; every true
    closure of the public graphs with 500 or more has a deletion χ² below a third of the
    cap at the optimum. Fewer closures measure the 99th percentile from fewer than five
    above it, so a few false ones among them would set it (kitti_00's 137 closures, by
    its 96th percentile, would have capped it at 1.2 times its largest true deletion χ²).
    Only ever tightens: false closures among the accepted ones raise the cap."""
    if np.count_nonzero(accepted) < TAIL_MIN_CLOSURES:
        return c2
    cap = factor * float(np.quantile(r2[accepted], TAIL_QUANTILE))
    return np.where(closures, np.minimum(c2, cap), c2)


#: The quantile of the accepted closures' squared residuals :func:`tail_thresholds` caps
#: ``c̄²`` from (the 99th: false closures among thousands of true ones do not move it).
TAIL_QUANTILE = 0.99
#: Fewest accepted closures :func:`tail_thresholds` caps ``c̄²`` from.
TAIL_MIN_CLOSURES = 500


def loop_closures(kind: np.ndarray, trusted: np.ndarray) -> np.ndarray:
    """The relative edges the robust solve weighs (GPS fixes are the other untrusted edges)."""
    return ~trusted & (kind == EdgeKind.RELATIVE)


def decided_thresholds(graph: PoseGraph, trusted: np.ndarray, config: RobustConfig,
                       weights: Array, r2: Array | None = None) -> Array:
    """:func:`edge_thresholds` capped by the tail of the closures ``weights`` accepted
    (:func:`tail_thresholds`), at the graph's poses or at the residuals ``r2``."""
    c2 = edge_thresholds(graph, trusted, config)
    r2 = edge_chi2(graph) if r2 is None else r2
    closures = loop_closures(graph.kind, trusted)
    return tail_thresholds(r2, closures, closures & (np.nan_to_num(weights) > 0.5), c2,
                           config.tail_factor)


def closure_noise_scale(graph: PoseGraph, trusted: np.ndarray) -> float:
    """The loop closures' real noise as a share of the covariance their information states
    (1: as stated), from pairs of closures of one revisit (ends within
    :data:`CLUSTER_SPAN` poses of each other's): one closure, carried to the other's ends
    along the dead-reckoned odometry between them, predicts the other, and the median χ²
    of that prediction (half its stated information: two closures' noise) over the median
    of χ² with its degrees of freedom is the scale. From the odometry, not the map: a map
    the false closures bent inflates every residual (parking-garage's median residual at
    least squares with 100 false closures is 4,000 times the outlier-free one), while a
    short stretch of dead reckoning is as good as the map and a random false closure rarely
    has a neighbour (with 1000 false closures parking-garage's scale moves from 4.8e-5 to
    at most 6.1e-5). 1 with fewer than :data:`MIN_PAIRS` pairs."""
    closures = np.flatnonzero(~trusted & (graph.kind == EdgeKind.RELATIVE) & (graph.a >= 0))
    first, second = _revisit_pairs(graph.a[closures], graph.b[closures])
    if len(first) < MIN_PAIRS:
        return 1.0
    one, other = closures[first], closures[second]
    R, t = odometry_chain(graph)
    a, b = graph.a, graph.b
    # The second closure predicted: X_a2⁻¹ X_a1 · Z_1 · X_b1⁻¹ X_b2.
    R_p, t_p = geo.compose(*geo.between(R[a[other]], t[a[other]], R[a[one]], t[a[one]]),
                           graph.meas_R[one], graph.meas_t[one])
    R_p, t_p = geo.compose(R_p, t_p, *geo.between(R[b[one]], t[b[one]], R[b[other]],
                                                   t[b[other]]))
    ident = np.broadcast_to(np.eye(3), R_p.shape)
    err = geo.relative_error(ident, np.zeros_like(t_p), R_p, t_p, graph.meas_R[other],
                             graph.meas_t[other])[:, graph.dof]
    info = graph.info[np.ix_(other, graph.dof, graph.dof)]
    chi2 = 0.5 * np.einsum("ei,eij,ej->e", err, info, err)
    chi2 = chi2[np.isfinite(chi2)]  # extreme values that overflow say nothing of the noise
    if len(chi2) < MIN_PAIRS:
        return 1.0
    return float(np.median(chi2) / chdtri(len(graph.dof), 0.5))


def _revisit_pairs(a: np.ndarray, b: np.ndarray, reach: int = 3
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``(i, j)`` of closures, each with up to ``reach`` next ones in ``(a, b)``
    order, whose ends are within :data:`CLUSTER_SPAN` poses of each other's."""
    order = np.lexsort((b, a))
    a, b = a[order], b[order]
    first, second = [], []
    for d in range(1, reach + 1):
        near = np.flatnonzero((np.abs(a[d:] - a[:-d]) <= CLUSTER_SPAN)
                              & (np.abs(b[d:] - b[:-d]) <= CLUSTER_SPAN))
        first.append(order[near])
        second.append(order[near + d])
    return np.concatenate(first), np.concatenate(second)


#: Fewest closure pairs :func:`closure_noise_scale` estimates from.
MIN_PAIRS = 20


def tls_weights(r2: Array, mu: float, c2: Array) -> Array:
    """GNC-TLS weights (Yang et al. 2020, eq. 14) of squared residuals ``r2`` at ``μ``:
    1 below ``μ/(μ+1) c̄²``, 0 above ``(μ+1)/μ c̄²``, ``c̄/r √(μ(μ+1)) − μ`` between."""
    r2 = np.asarray(r2, dtype=float)
    lo = mu / (mu + 1.0) * c2
    hi = (mu + 1.0) / mu * c2
    with np.errstate(all="ignore"):  # r² = 0 or tiny: that branch is not taken
        mid = np.sqrt(c2 / r2) * math.sqrt(mu * (mu + 1.0)) - mu
    return np.where(r2 <= lo, 1.0, np.where(r2 >= hi, 0.0, np.clip(mid, 0.0, 1.0)))


def initial_mu(r2_max: float, c2: float) -> float:
    """``μ₀ = c̄² / (2 r²_max − c̄²)``: the surrogate is convex over every residual."""
    return c2 / max(2.0 * r2_max - c2, 1e-12 * c2)


def edge_states(weights: Array, trusted: np.ndarray) -> np.ndarray:
    """:class:`EdgeState` of each edge from its weight."""
    states = np.full(len(weights), EdgeState.DOWNWEIGHTED, dtype=np.int8)
    states[weights >= 1.0 - WEIGHT_TOLERANCE] = EdgeState.ACCEPTED
    states[weights <= WEIGHT_TOLERANCE] = EdgeState.DROPPED
    states[trusted] = EdgeState.TRUSTED
    return states


def solver_residuals(solver: H2OSolver) -> Array:
    """Unweighted χ² of each of the solver's edges at its current estimate."""
    return edge_chi2(solver.graph(copy=False))


def converge_robust(
    solver: H2OSolver, iterations: int, trusted: np.ndarray,
    config: RobustConfig | None = None, weights: Array | None = None,
    restart: Restart | None = None, regraduate: bool = False,
) -> RobustOutcome:
    """GNC-TLS over the solver's edges (module docstring), then Gauss–Newton to convergence
    with the final 0/1 weights.

    ``trusted``: edges whose weight stays 1 (odometry). ``weights``: a previous solution's
    decisions (0 or 1, NaN for edges it did not hold), for a solve carried on
    (:func:`carry_on`); ``None`` graduates from least squares (all 1). ``restart``: world
    poses ``(R, t)`` to start a solve with given weights from (LAGO of the weighted graph,
    for planar graphs), tried when a warm-started re-admission fails. ``regraduate``: with
    ``weights``, also graduate afresh and keep the answer of lowest TLS cost, even when the
    carried decisions raise no doubt (an explicit exact solve: decisions carried on through
    a stream with many false closures can have settled in a local minimum).
    """
    cfg = config or RobustConfig()
    start = (solver.tree.R.copy(), solver.tree.t.copy())
    outcome = _decide(solver, iterations, trusted, cfg, weights, restart)
    if not outcome.converged:
        _polish(solver, outcome, start, iterations)
    if regraduate and weights is not None:
        outcome = _fresh_if_lower(solver, iterations, trusted, cfg, restart, outcome, start)
    # With every edge kept the answer is least squares of the whole graph, which a batch
    # solve already starts from LAGO (planar) or chordal (3-D, its default start); a
    # restart there would only repeat it.
    if restart is not None and np.any(outcome.weights < 1.0):
        restarted_if_lower(solver, outcome, restart, iterations)
    return outcome


def lowest_cost(graph: PoseGraph, trusted: np.ndarray, config: RobustConfig,
                answers: list[tuple[Array, Array]]) -> int:
    """Which of ``answers`` (each: every edge's weight and unweighted χ²) has the lowest TLS
    cost, scored at the tightest thresholds any answer's accepted closures allow: at its
    own, an answer that kept a false closure its tail would refuse scores lower."""
    c2 = np.min([decided_thresholds(graph, trusted, config, w, r2) for w, r2 in answers],
                axis=0)
    return int(np.argmin([tls_cost(r2, ~trusted, c2) for _, r2 in answers]))


def _start_at(solver: H2OSolver, start: tuple[Array, Array] | Array,
              restart: Restart | None) -> None:
    """Put the solver's map at ``start``: tree poses ``(R, t)``, or the restart from these
    weights."""
    if isinstance(start, tuple):
        solver.tree.R[:], solver.tree.t[:] = start
    else:
        assert restart is not None
        solver.tree.set_world_poses(*restart(start))


def _fresh_if_lower(solver: H2OSolver, iterations: int, trusted: np.ndarray,
                    cfg: RobustConfig, restart: Restart | None, carried: RobustOutcome,
                    seed: tuple[Array, Array]) -> RobustOutcome:
    """The carried answer (the solver's map now) or a graduation from scratch, as a batch
    solve runs it (from LAGO of the odometry and of every edge, or from ``seed`` without a
    restart), whichever has the lowest TLS cost at the tightest thresholds any answer's
    accepted closures allow (at its own, an answer keeping a false closure its tail would
    refuse scores lower). Never above the carried answer's TLS cost; what it buys varies:
    on manhattan as the node builds it, with 1,000 random false closures streamed, one run
    ended on the outlier-free map where the carried decisions had kept a false closure
    (5.8 m off), another kept the carried answer, and it costs the explicit solve several
    graduations (about 6 minutes there; seconds with tens of false closures)."""
    answers = [(solver.tree.R.copy(), solver.tree.t.copy(), carried)]
    starts: list[tuple[Array, Array] | Array] = [seed]
    if restart is not None:
        starts = [trusted.astype(float), np.ones(solver.num_edges)]
    for start in starts:
        _start_at(solver, start, restart)
        begin = (solver.tree.R.copy(), solver.tree.t.copy())
        fresh = _decide(solver, iterations, trusted, cfg, None, restart)
        if not fresh.converged:
            _polish(solver, fresh, begin, iterations)
        answers.append((solver.tree.R.copy(), solver.tree.t.copy(), fresh))
    scored = []
    for R, t, answer in answers:
        solver.tree.R[:], solver.tree.t[:] = R, t
        scored.append((answer.weights, solver_residuals(solver)))
    R, t, outcome = answers[lowest_cost(solver.graph(copy=False), trusted, cfg, scored)]
    solver.tree.R[:], solver.tree.t[:] = R, t
    solver.set_weights(outcome.weights)
    return outcome


def _polish(solver: H2OSolver, outcome: RobustOutcome, start: tuple[Array, Array],
            iterations: int) -> None:
    """The final decisions solved again from the solve's own start, kept if χ² ends lower.
    A solve that ends unconverged ends on a map bent by decisions it later reversed, where
    Gauss–Newton crawls: parking-garage with 100 false closures, every decision right,
    stopped after 619 iterations at 1.086 times the optimum, which the same decisions reach
    in 4 iterations from the odometry's tree."""
    bent = (solver.tree.R.copy(), solver.tree.t.copy())
    solver.tree.R[:], solver.tree.t[:] = start
    history, converged = converge_exact(solver, iterations)
    if history[-1] < outcome.history[-1]:
        outcome.history.extend(history[1:])
        outcome.converged = converged
    else:
        solver.tree.R[:], solver.tree.t[:] = bent


def restarted_if_lower(solver: H2OSolver, outcome: RobustOutcome, restart: Restart,
                       iterations: int) -> None:
    """The final decisions solved again from the restart of these decisions (LAGO of the
    kept edges, planar; chordal, 3-D), kept if χ² ends lower. Decisions made along a
    graduation can leave least squares converged in a basin of their own that the same
    decisions from a cold start avoid: intel with 10 grouped false closures as the node
    builds it, every decision right, converged at χ² 171.18 where LAGO of the same
    decisions converges to 49.73 (the maps 25 m apart at the farthest pose)."""
    here = (solver.tree.R.copy(), solver.tree.t.copy())
    current = float(solver_residuals(solver) @ outcome.weights)
    _start_at(solver, outcome.weights, restart)
    history, converged = converge_exact(solver, iterations)
    # Lower by more than the solve's own tolerance: a loosely converged answer is not
    # replaced by the restart's few more iterations toward the same optimum.
    if converged and not settled(current, history[-1], solver.config.exact_tolerance):
        outcome.history.extend(history[1:])
        outcome.converged = True
    else:
        solver.tree.R[:], solver.tree.t[:] = here


def _decide(solver: H2OSolver, iterations: int, trusted: np.ndarray, cfg: RobustConfig,
            weights: Array | None, restart: Restart | None) -> RobustOutcome:
    """The decisions of :func:`converge_robust`, the map at them in ``solver``."""
    graph = solver.graph(copy=False)
    if weights is None:
        c2 = edge_thresholds(graph, trusted, cfg)
        return _tightened(solver, iterations, trusted, c2, cfg, restart,
                          _graduate(solver, iterations, ~trusted, c2, cfg, restart))
    # The previous decisions at the warm start's map set the closures' tail.
    c2 = decided_thresholds(graph, trusted, cfg, weights, solver_residuals(solver))
    seed = (solver.tree.R.copy(), solver.tree.t.copy())
    outcome, doubt = carry_on(solver, iterations, trusted, c2, weights, restart, cfg)
    if outcome is not None and not doubt:
        return outcome
    # A new edge refused, or an accepted one contradicted: the earlier decisions may be
    # what is wrong (a false closure accepted while its loop was open), so graduate again
    # and keep the answer of lowest TLS cost. From the seed and, with a cold start, from
    # LAGO of every edge and of the odometry alone: the seed may be bent by the decisions
    # in doubt, and which start avoids least squares' local minima depends on the graph.
    best = None if outcome is None else _scored(solver, trusted, c2, outcome)
    starts: list[tuple[Array, Array] | Array] = [seed]
    if restart is not None:
        starts += [np.ones(solver.num_edges), trusted.astype(float)]
    for start in starts:
        _start_at(solver, start, restart)
        graduated = _scored(solver, trusted, c2,
                            _graduate(solver, iterations, ~trusted, c2, cfg, restart))
        if best is None or graduated[0] < best[0]:
            best = graduated
    assert best is not None
    solver.tree.R[:], solver.tree.t[:] = best[1], best[2]
    solver.set_weights(best[3].weights)
    return best[3]


def _tightened(solver: H2OSolver, iterations: int, trusted: np.ndarray, c2: Array,
               cfg: RobustConfig, restart: Restart | None, outcome: RobustOutcome
               ) -> RobustOutcome:
    """The graduation's decisions settled again at the thresholds their accepted closures'
    tail allows (:func:`tail_thresholds`), where those are tighter."""
    closures = loop_closures(solver.kind[:solver.num_edges], trusted)
    w = outcome.weights
    tight = tail_thresholds(solver_residuals(solver), closures, closures & (w > 0.5), c2,
                            cfg.tail_factor)
    if np.array_equal(tight, c2):
        return outcome
    outcome.converged = _settle(solver, w, ~trusted, tight, iterations, outcome.history,
                                restart, cfg.inlier_probability, converged=outcome.converged)
    return outcome


def _scored(solver: H2OSolver, trusted: np.ndarray, c2: Array, outcome: RobustOutcome
            ) -> tuple[float, Array, Array, RobustOutcome]:
    """An outcome with the TLS cost and the poses it left the solver at."""
    return (tls_cost(solver_residuals(solver), ~trusted, c2), solver.tree.R.copy(),
            solver.tree.t.copy(), outcome)


def carry_on(solver: H2OSolver, iterations: int, trusted: np.ndarray, c2: Array,
             weights: Array, restart: Restart | None, config: RobustConfig
             ) -> tuple[RobustOutcome | None, bool]:
    """The online solve: keep the previous decisions, admit each new edge whose innovation
    against the map without it is within ``c̄²`` (so the first closure of a long loop is
    weighed by the map's uncertainty along the loop, not by its own covariance alone),
    and settle. Returns the outcome (``None`` when an accepted edge is contradicted, its
    residual above ``c̄²``) and whether a new edge was refused."""
    free = ~trusted
    w = np.asarray(weights, dtype=float).copy()
    new = np.flatnonzero(free & np.isnan(w))
    w[np.isnan(w) | trusted] = 1.0
    w[new] = 0.0
    solver.set_weights(w)
    history, converged = converge_exact(solver, iterations)
    admitted = new
    if len(new):
        admitted = new[innovation_chi2(solver, new) <= c2[new]]
        if len(admitted):
            w[admitted] = 1.0
            solver.set_weights(w)
            more, converged = converge_exact(solver, iterations)
            history.extend(more[1:])
    doubt = len(admitted) < len(new)
    if np.any(free & (w > 0.5) & (solver_residuals(solver) > c2)):
        return None, doubt
    converged = _settle(solver, w, free, c2, iterations, history, restart,
                        config.inlier_probability, converged=converged)
    return RobustOutcome(w, history, 0, converged), doubt


def _graduate(solver: H2OSolver, iterations: int, free: np.ndarray, c2: Array,
              cfg: RobustConfig, restart: Restart | None) -> RobustOutcome:
    """GNC from least squares over every edge, then :func:`_settle`."""
    w = np.ones(solver.num_edges)
    solver.set_weights(w)
    history, converged = converge_exact(solver, iterations)
    r2 = solver_residuals(solver)
    steps = 0
    if np.any(free & (r2 > c2)):
        mu = initial_mu(float(np.max(r2[free] / c2[free])), 1.0)
        for steps in range(1, cfg.max_steps + 1):  # noqa: B007 - the count is reported
            w[free] = tls_weights(r2[free], mu, c2[free])
            solver.set_weights(w)
            more, _ = converge_exact(solver, cfg.inner_iterations)
            history.extend(more[1:])
            r2 = solver_residuals(solver)
            if _binary(w[free]) and mu > 1e3:
                break
            mu *= cfg.mu_factor
    # Least squares can also absorb an outlier among many inliers: its residual spread
    # below c̄² while the TLS cost without it is a fifth (measured on a revisit: 135
    # against 26), so edges under strain are tried out even when none exceeds c̄².
    if steps or np.any(free & (r2 > STRAIN * c2)):
        # After graduation steps the map is at capped solves; without, least squares'.
        converged = _settle(solver, w, free, c2, iterations, history, restart,
                            cfg.inlier_probability, converged=converged and not steps)
    return RobustOutcome(w, history, steps, converged)


def _settle(solver: H2OSolver, w: Array, free: np.ndarray, c2: Array, iterations: int,
            history: list[float], restart: Restart | None, probability: float,
            rounds: int = 10, converged: bool = False) -> bool:
    """From the graduation's end to a local minimum of the TLS cost that re-admission cannot
    lower.

    Closures dropped while the map was still bent are tried again by place
    (:func:`_clusters`, the most plausible by innovation first, :func:`innovation_chi2`):
    a cluster comes back, the accepted edges are re-tested, and the move is kept only if
    the TLS cost fell. By cluster, because closures that only agree with each other (a
    revisit the graduation cut loose) each look doubtful alone: measured on intel, a
    revisit of 6 true closures dropped for a TLS cost of 931 where the outlier-free map's
    is 304.

    Last, a place whose closures are jointly incompatible with the map built without them
    (:func:`_incompatible_place`) is dropped whatever the TLS cost says, and its closures
    stay out of this solve's re-admissions unless one fits the map built without it as an
    ordinary inlier (:func:`release_ratio`); the moves then run again. ``converged``: the
    map is converged at the weights ``w`` already.
    """
    converged = _tls_rounds(solver, w, free, c2, iterations, history, converged=converged)
    start = len(history)
    vetoed = np.zeros(len(w), dtype=bool)
    for _ in range(rounds):
        converged = _local_moves(solver, w, free, c2, iterations, history, restart,
                                 converged, rounds, vetoed, probability)
        place = _incompatible_place(solver, w, free, c2, probability)
        if place is None:
            break
        w[place] = 0.0
        solver.set_weights(w)
        converged = _tls_rounds(solver, w, free, c2, iterations, history, solve_first=True)
        # A place is where the closures' ends are, not which of them are wrong: a true
        # closure of the same revisit as a consistent false group fits the map built
        # without the place as an ordinary inlier does and may come back (intel with 100
        # grouped false closures: two true closures at 0.001 c̄² stayed out beside a group
        # of ten, χ² 1.0046 times the optimum). Members of a place found incompatible are
        # suspect, so the bar is the inliers' RELEASE_TAIL quantile, not c̄²: the false
        # members there sat at 0.5-3.9 c̄², and at c̄² two of them came back on the node's
        # graph.
        bar = c2[place] * release_ratio(solver.p, probability)
        vetoed[place] = innovation_chi2(solver, place) > bar
    if len(history) > start:  # moves were tried on capped solves: finish the last one
        converged = _tls_rounds(solver, w, free, c2, iterations, history, solve_first=True)
    return converged


def _local_moves(solver: H2OSolver, w: Array, free: np.ndarray, c2: Array, iterations: int,
                 history: list[float], restart: Restart | None, converged: bool,
                 rounds: int, vetoed: np.ndarray, probability: float) -> bool:
    """Re-admissions of the ``free`` edges that are out (not ``vetoed``), and drop moves,
    while one helps."""
    for _ in range(rounds):
        moved = False
        out = np.flatnonzero(free & (w < 0.5))
        if len(out):
            ratio = innovation_chi2(solver, out) / c2[out]
            ratio[vetoed[out]] = np.inf
            fitting = out[ratio <= 1.0]
            if len(fitting) > 1:
                # Every closure the map already agrees with, at once: one by one, eight
                # tries a round left 702 of city10000's true closures out beside 1,000
                # grouped false ones.
                kept, converged = _try_move(solver, w, free, c2, fitting, 1.0, iterations,
                                            history, converged, restart)
                if kept:
                    continue
            # The plausible members of each place: a false closure dropped beside true
            # ones of the same revisit stays out when they come back.
            groups = [g[ratio[g] <= READMIT]
                      for g in _clusters(solver.a[out], solver.b[out], ratio)
                      if ratio[g].min() <= READMIT]
            tries = 0
            for group in groups:
                # The place together, else its members one by one, most plausible first.
                for part in [group] + ([group[[i]] for i in np.argsort(ratio[group])]
                                       if len(group) > 1 else []):
                    if tries == MAX_TRIES:
                        break
                    tries += 1
                    kept, converged = _try_move(solver, w, free, c2, out[part], 1.0,
                                                iterations, history, converged, restart)
                    moved |= kept
                    if kept:
                        break
        if not (moved or _drop_strained(solver, w, free, c2, iterations, history, restart,
                                        probability)):
            break
    return converged


def _incompatible_place(solver: H2OSolver, w: Array, free: np.ndarray, c2: Array,
                        probability: float) -> np.ndarray | None:
    """The accepted closures of the place least compatible with the map built without them,
    if their joint deletion χ² (:func:`group_chi2`: their joint innovation against that
    map, to first order) exceeds the χ² quantile of their joint degrees of freedom at the
    inlier ``probability``, scaled as the closures' ``c̄²`` (:func:`edge_thresholds`);
    else ``None``. The joint compatibility test of data association
    (Neira & Tardós, "Data association in stochastic mapping using the joint compatibility
    test", IEEE T-RA 2001), applied to one revisit: the TLS cost alone can prefer a group of
    consistent false closures that a weakly tied map bends to fit (measured on intel with
    100 grouped false closures: accepting a group of 8 cost less than leaving it out, while
    its joint deletion χ² was 1.4 times the quantile and no true place's above 0.2)."""
    inside = np.flatnonzero(free & (w > 0.5))
    if not _every_scored(solver, inside):
        return None
    closures = inside[solver.kind[inside] == EdgeKind.RELATIVE]
    # A revisit, not the chain of revisits that clustering joins on a much-travelled
    # corridor (hundreds of closures: its test would cost seconds and say nothing).
    places = [closures[g] for g in _clusters(solver.a[closures], solver.b[closures],
                                             np.zeros(len(closures))) if len(g) <= MAX_PLACE]
    if not places:
        return None
    ratio = group_chi2(solver, places, sign=-1.0) / _compatible_up_to(
        solver.p, c2, places, probability)
    worst = int(np.argmax(ratio))
    return places[worst] if ratio[worst] > 1.0 else None


def _compatible_up_to(p: int, c2: Array, places: list[np.ndarray], probability: float
                      ) -> Array:
    """The joint compatibility test's bar for each place (edges of ``c2``): the χ²
    quantile of its joint degrees of freedom at the inlier ``probability``, scaled as its
    closures' ``c̄²`` (:func:`edge_thresholds`)."""
    dof = np.array([len(g) * p for g in places])
    # Each place's ``c̄²`` over the unscaled one: the noise scale its thresholds carry.
    scale = np.array([c2[g].max() for g in places]) / chdtri(p, 1.0 - probability)
    return chdtri(dof, 1.0 - probability) * scale


#: Largest place (closures) whose joint compatibility is tested.
MAX_PLACE = 32

#: A member of a place the joint compatibility test dropped comes back only with an
#: innovation within this upper-tail quantile of χ² (an ordinary inlier's, 0.99).
RELEASE_TAIL = 0.01


def release_ratio(dof: int, probability: float) -> float:
    """The release bar of a dropped place's members as a share of ``c̄²``: the χ² quantile
    at :data:`RELEASE_TAIL` over the one at the inlier ``probability`` (0.37 for a planar
    closure at the default 0.999999)."""
    return float(chdtri(dof, RELEASE_TAIL) / chdtri(dof, 1.0 - probability))


#: Gauss–Newton iterations a trial move gets before its TLS cost is compared (a move kept
#: is solved to convergence at the end): trials are most of a robust solve's time.
TRIAL_ITERATIONS = 15


def _drop_strained(solver: H2OSolver, w: Array, free: np.ndarray, c2: Array, iterations: int,
                   history: list[float], restart: Restart | None, probability: float) -> bool:
    """Try dropping accepted closures that hold the map against the rest: those whose
    removal would lower the cost most (:func:`deletion_chi2` beyond ``c̄²``: a false
    closure that alone ties a weakly held stretch fits the map it bent, its strain spread
    over the trusted odometry), those under the most strain, and places with several (a
    group of mutually consistent false closures); returns whether a drop was kept."""
    inside = np.flatnonzero(free & (w > 0.5))
    if not len(inside):
        return False
    ratio = solver_residuals(solver)[inside] / c2[inside]
    strained = ratio > STRAIN
    order = [i for i in np.argsort(-ratio)[:MAX_TRIES] if strained[i]]
    places: list[np.ndarray] = []
    every = _every_scored(solver, inside)
    if every:
        shared = _places(solver, inside)
        # Each closure alone and each place in one scoring: a place's entries of H⁻¹ are
        # its closures' own.
        joint = group_chi2(solver, [inside[[i]] for i in range(len(inside))]
                           + [inside[g] for g in shared], sign=-1.0)
        # The deletion χ² is, to first order, the dropped edge's innovation after the drop:
        # below SIGNIFICANT × c̄² the move would be refused, so it is not tried.
        deletion = joint[:len(inside)] / c2[inside]
        strained &= deletion > SIGNIFICANT
        order = [i for i in np.argsort(-deletion)[:MAX_TRIES] if deletion[i] > SIGNIFICANT]
        order += [i for i in np.argsort(-ratio)[:MAX_TRIES] if strained[i]]
        places = _held_places(solver.p, inside, c2, shared, joint[len(inside):], probability)
    # Single closures first (a false closure among true ones of the same revisit shares
    # their place, so its cluster would take them out with it), then whole places.
    singles = [np.array([i]) for i in dict.fromkeys(order)]
    groups = [np.flatnonzero(strained)[g] for g in _clusters(
        solver.a[inside[strained]], solver.b[inside[strained]], -ratio[strained]) if len(g) > 1]
    candidates = singles + groups[:MAX_TRIES]
    if not every:
        candidates = _significant_drops(solver, inside, c2, candidates)
    moved = False
    for group in candidates + places:
        kept, _ = _try_move(solver, w, free, c2, inside[group], 0.0, iterations, history,
                            False, restart)
        moved |= kept
    return moved


def _every_scored(solver: H2OSolver, inside: np.ndarray) -> bool:
    """Whether every one of the ``inside`` closures gets its deletion χ² (and every place
    its joint one) in a settling round, or only the strained ones (:data:`DELETION_WORK`)."""
    return len(inside) * solver.num_nodes * solver.p <= DELETION_WORK


def _significant_drops(solver: H2OSolver, inside: np.ndarray, c2: Array,
                       candidates: list[np.ndarray]) -> list[np.ndarray]:
    """The drop candidates (positions in ``inside``) whose joint deletion χ² exceeds
    :data:`SIGNIFICANT` times their summed ``c̄²``: to first order, what dropping them saves
    against what the dropped closures then cost, the test a drop move must pass, here on
    the few candidates where every accepted closure's deletion χ² would cost too much.
    Measured on a 2,200-pose sphere with σ_R 0.1 rad and no false closure: 16 drops chosen
    by strain alone were tried, none kept, 45 of the robust solve's 48 s."""
    if not candidates:
        return []
    groups = [inside[g] for g in candidates]
    bar = SIGNIFICANT * np.array([c2[g].sum() for g in groups])
    joint = _screened_deletion(solver, groups, bar)
    return [g for g, chi2, most in zip(candidates, joint, bar, strict=True) if chi2 > most]


def _screened_deletion(solver: H2OSolver, groups: list[np.ndarray], bars: Array) -> Array:
    """Each group's deletion χ² (:func:`group_chi2`, ``sign`` −1) where it may exceed its
    bar, else an upper bound on it at most the bar: the edges around each group bound it
    first (:func:`~h2o_slam.core.neighbourhood.deletion_bounds` at each of
    :data:`BOUND_HOPS`, the map's Jacobians taken once for all of them), and only the
    groups no bound clears are scored on the whole graph. The whole graph's
    covariance at a few closures costs a factorization and a selected inverse (0.35 s on a
    2,200-pose sphere), a closure's neighbourhood tens of microseconds."""
    out = np.full(len(groups), np.nan)
    doubt = np.arange(len(groups))
    around = Neighbourhoods(solver)
    for hops in BOUND_HOPS:
        if not len(doubt):
            break
        bound = around.bounds([groups[i] for i in doubt], hops)
        cleared = bound <= bars[doubt]
        out[doubt[cleared]] = bound[cleared]
        doubt = doubt[~cleared]
    out[doubt] = group_chi2(solver, [groups[i] for i in doubt], sign=-1.0)
    return out


#: Neighbourhoods (edges from a group's ends) whose bounds on its deletion χ² are tried,
#: the smaller first: one edge clears every strained closure of the 2,200-pose spheres,
#: two every closure of city10000 (one 86 %).
BOUND_HOPS = (1, 2)


def _places(solver: H2OSolver, inside: np.ndarray) -> list[np.ndarray]:
    """Places of several accepted loop closures (positions in ``inside``, :func:`_clusters`).
    Loop closures only: GPS fixes share no place (their first end is the earth), and a run
    of jumped fixes is the GPS gate's to hold."""
    closures = np.flatnonzero(solver.kind[inside] == EdgeKind.RELATIVE)
    return [closures[g] for g in _clusters(solver.a[inside[closures]],
                                           solver.b[inside[closures]],
                                           np.zeros(len(closures))) if len(g) > 1]


def _held_places(p: int, inside: np.ndarray, c2: Array, places: list[np.ndarray],
                 joint: Array, probability: float) -> list[np.ndarray]:
    """The ``places`` (positions in ``inside``) whose joint deletion χ² ``joint``
    (:func:`group_chi2`) fails the joint compatibility test (:func:`_compatible_up_to`
    at the inlier ``probability``), largest share of their summed ``c̄²`` first: a group of
    consistent false closures holds a bent stretch together, each one's own deletion χ²
    small because the others hold it (measured on intel with a group of 10: two accepted,
    deletion χ² 0.93 and 0.34 ``c̄²`` each, 4.6 times the pair's summed ``c̄²`` together,
    where the next place is at 0.15; on MIT, ten accepted at 1.05 times, the next at 0.14).
    A place that passes cannot be dropped (each member would have to contradict the map
    built without it by :data:`SIGNIFICANT` ``c̄²``), yet trying cost a trial solve each:
    smallGrid3D's place of 164 closures, 60 % of its robust solve."""
    if not places:
        return []
    ratio = joint / np.array([c2[inside[g]].sum() for g in places])
    bars = _compatible_up_to(p, c2, [inside[g] for g in places], probability)
    return [places[i] for i in np.argsort(-ratio)[:MAX_TRIES] if joint[i] > bars[i]]


#: Largest (accepted closures × unknowns) for which a drop round scores every closure's
#: :func:`deletion_chi2` and every place's joint one; beyond it the strained closures are
#: the candidates. Once the bound on columns of ``H⁻¹`` (intel's 785 closures × 5184
#: unknowns took ~1 s); with the selected inverse the scoring costs tens of milliseconds,
#: but more candidates are tried, each a trial solve: every closure scored, manhattan's
#: robust solve took 0.48 s instead of 0.22, parking-garage's 1.74 instead of 0.39, the
#: same maps.
DELETION_WORK = 1e7


#: Accepted closures whose residual is above this share of ``c̄²`` are tried out.
STRAIN = 0.25


#: Clusters are tried again when one of their closures has an innovation within this many
#: times ``c̄²`` (a false closure of the benchmark's kind is at 20-130 times).
READMIT = 4.0
#: Re-admission attempts per round (the most plausible clusters first).
MAX_TRIES = 8
#: Closures whose ends are both within this many poses of another's are one cluster.
CLUSTER_SPAN = 10


def _clusters(a: np.ndarray, b: np.ndarray, ratio: Array) -> list[np.ndarray]:
    """Dropped closures grouped by place (both ends within :data:`CLUSTER_SPAN` poses of a
    member's), most plausible group (lowest innovation over ``c̄²``) first: a revisit's
    closures agree with each other, and each alone may not outweigh the map it bent."""
    from scipy.sparse.csgraph import connected_components  # on use: see chdtri

    k = len(a)
    i, j = _near_pairs(np.asarray(a), np.asarray(b))
    near = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(k, k))
    _, label = connected_components(near.tocsr(), directed=False)
    order = np.argsort(label, kind="stable")
    groups = np.split(order, np.flatnonzero(np.diff(label[order])) + 1) if k else []
    groups.sort(key=lambda g: float(np.min(ratio[g])))
    return groups


def _near_pairs(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of closures whose ``a`` ends and ``b`` ends are each within
    :data:`CLUSTER_SPAN` poses: along ``a``'s order, the pairs ``step`` apart for each
    ``step`` until none is that close in ``a`` (a comparison of every pair was 1.1 s of
    parking-garage's robust solve, 4,600 closures)."""
    order = np.argsort(a, kind="stable")
    sa, sb = a[order], b[order]
    rows, cols = [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)]
    for step in range(1, len(a)):
        near = sa[step:] - sa[:-step] <= CLUSTER_SPAN
        if not near.any():
            break
        pos = np.flatnonzero(near & (np.abs(sb[step:] - sb[:-step]) <= CLUSTER_SPAN))
        rows.append(order[pos])
        cols.append(order[pos + step])
    return np.concatenate(rows), np.concatenate(cols)


def _try_move(solver: H2OSolver, w: Array, free: np.ndarray, c2: Array, edges: np.ndarray,
              weight: float, iterations: int, history: list[float], converged: bool,
              restart: Restart | None) -> tuple[bool, bool]:
    """Set ``edges``' weight (1: re-admit, 0: drop), re-test the accepted edges, and keep
    the result only if the TLS cost fell; from the current map first, then from
    ``restart``'s start for the new weights (a map bent while a revisit was out can sit in a
    local minimum of least squares that the revisit alone does not pull it out of).
    Returns whether the move was kept and whether the last solve converged."""
    cost = tls_cost(solver_residuals(solver), free, c2)
    saved = (solver.tree.R.copy(), solver.tree.t.copy(), w.copy(), len(history))
    for start in (None, restart):
        if start is not None:
            trial = np.where(free, 1.0 * (w > 0.5), 1.0)
            trial[edges] = weight
            solver.tree.set_world_poses(*start(trial))
        w[edges] = weight
        solver.set_weights(w)
        now = _tls_rounds(solver, w, free, c2, min(iterations, TRIAL_ITERATIONS), history,
                          solve_first=True)
        after = tls_cost(solver_residuals(solver), free, c2)
        if after < cost * (1.0 - 1e-9) and (weight > 0.0 or _significant(solver, edges, c2)):
            return True, now
        # A closure that fits costs the TLS objective the same in or out (min(r², c̄²) = r²):
        # one that comes back and stays within c̄² is kept if the cost did not rise.
        if weight > 0.0 and after <= cost * (1.0 + 1e-9) and np.all(w[edges] > 0.5):
            return True, now
        solver.tree.R[:], solver.tree.t[:], w[:] = saved[0], saved[1], saved[2]
        del history[saved[3]:]
        solver.set_weights(w)
        if restart is None:
            break
    return False, converged


def _significant(solver: H2OSolver, dropped: np.ndarray, c2: Array) -> bool:
    """Every dropped edge contradicts the map built without it: its innovation (its own
    covariance plus the map's uncertainty between its ends) is above :data:`SIGNIFICANT`
    times ``c̄²``. A TLS cost that falls is not enough: on manhattan, without outliers,
    dropping two true closures that hold a weakly tied stretch lowered it by 3.8 of 3549
    (their innovations then 26.0 and 29.6, under ``c̄²`` = 30.7). A false closure can sit
    close to the bar: on MIT, a local one at 1.15 ``c̄²``."""
    return bool(np.all(innovation_chi2(solver, dropped) > SIGNIFICANT * c2[dropped]))


#: How far beyond ``c̄²`` a dropped edge's innovation must lie for a drop move to stand
#: (33.8 for a planar closure).
SIGNIFICANT = 1.1


def tls_cost(r2: Array, free: np.ndarray, c2: Array) -> float:
    """The objective: ``Σ r²`` of trusted edges plus ``Σ min(r², c̄²)`` of the others."""
    return float(np.sum(np.where(free, np.minimum(r2, c2), r2)))


def _tls_rounds(solver: H2OSolver, w: Array, free: np.ndarray, c2: Array, iterations: int,
                history: list[float], solve_first: bool = False, rounds: int = 20,
                converged: bool = False) -> bool:
    """Drop accepted edges whose residual exceeds ``c̄²`` and solve, until none does (each
    round lowers the TLS cost); dropped edges stay dropped. ``converged``: the map is
    converged at the weights ``w`` already, so that when no edge is dropped and no weight
    changes nothing is solved."""
    for i in range(rounds):
        if i or solve_first:
            more, converged = converge_exact(solver, iterations)
            history.extend(more[1:])
        r2 = solver_residuals(solver)
        bad = free & (w > 0.5) & (r2 > c2)
        if i and not bad.any():
            break
        kept = np.where(free, (w > 0.5) & ~bad, 1.0)
        if not (i or solve_first) and converged and np.array_equal(kept, w):
            break
        w[:] = kept
        solver.set_weights(w)
        converged = False
    return converged


def deletion_chi2(solver: H2OSolver, edges: np.ndarray) -> Array:
    """How much the optimal χ² of the map would fall without each of ``edges`` (each in it,
    weight 1): ``rᵀ (I − J Σ_map Jᵀ)⁻¹ r`` in whitened terms, the leave-one-out residual.
    Large for an edge the map bent to fit, however small its own residual."""
    return innovation_chi2(solver, edges, sign=-1.0)


def innovation_chi2(solver: H2OSolver, edges: np.ndarray, chunk: int = 128,
                    sign: float = 1.0) -> Array:
    """χ² of each of ``edges``' residuals against ``Σ_e + J Σ_map Jᵀ``: its own covariance
    plus the covariance of its ends' relative pose in the map of the current weights
    (``Σ_map = H⁻¹`` of the weighted Gauss–Newton system, so the edge's own weight should
    be 0). Edges whose ends the system holds fixed see only their own covariance. Where
    ``H`` cannot be factored, the plain residual χ². ``sign`` −1: ``Σ_e − J Σ_map Jᵀ``
    (:func:`deletion_chi2`)."""
    edges = np.asarray(edges, dtype=np.int64)
    return group_chi2(solver, [edges[[i]] for i in range(len(edges))], chunk, sign)


def group_chi2(solver: H2OSolver, groups: list[np.ndarray], chunk: int = 128,
               sign: float = 1.0) -> Array:
    """:func:`innovation_chi2` (``sign`` −1: :func:`deletion_chi2`) of each group of edges
    taken together: the stacked residual against the joint covariance, cross terms between
    the group's edges included. Two false closures that hold a stretch together each have a
    small deletion χ² (the other holds it), their joint one is large.

    Groups already scored at the same map, edges and weights are not scored again
    (:class:`_Scored`): a settling round tests every accepted closure alone, then its
    places for a drop, then the same places for joint compatibility, each a factorization
    and ``2p`` columns of ``H⁻¹`` a closure (a 1,000-pose 3-D grid without outliers: the
    places' second scoring was 1.6 of the robust solve's 4.4 s)."""
    if not groups:
        return np.zeros(0)
    scored = _Scored.at(solver, sign)
    keys = [tuple(sorted(np.asarray(g, dtype=np.int64).tolist())) for g in groups]
    todo = list(dict.fromkeys(k for k in keys if k not in scored))
    if todo:
        fresh = _group_chi2([np.array(k, dtype=np.int64) for k in todo], solver, chunk, sign)
        scored.update(zip(todo, fresh.tolist(), strict=True))
    return np.array([scored[k] for k in keys])


class _Scored:
    """The group χ² scored at one state of a solver (per thread): the map, the edges and
    their weights, hashed."""

    _local = threading.local()

    @classmethod
    def at(cls, solver: H2OSolver, sign: float) -> dict[tuple[int, ...], float]:
        """The groups scored so far at the solver's present state (a new, empty dict when
        the state changed since the last call)."""
        n, m = solver.num_nodes, solver.num_edges
        tree = solver.tree
        digest = hashlib.blake2b(np.float64(sign).tobytes(), digest_size=16)
        for arr in (tree.parent[:n], tree.R[:n], tree.t[:n], solver.a, solver.b, solver.kind,
                    solver.weight[:m], solver.meas_R, solver.meas_t, solver.info):
            digest.update(np.ascontiguousarray(arr).tobytes())
        key = (id(solver), n, m, digest.digest())
        local = cls._local
        if getattr(local, "key", None) != key:
            local.key, local.scored = key, {}
        scored: dict[tuple[int, ...], float] = local.scored
        return scored


def _group_chi2(groups: list[np.ndarray], solver: H2OSolver, chunk: int, sign: float
                ) -> Array:
    """:func:`group_chi2`, every group scored, each the cheapest way that serves: a group
    of more than :data:`LEFT_OUT_FROM` edges by one solve with them left out
    (:func:`_left_out_chi2`); the others from the selected inverse
    (:func:`_selected_chi2`) where it is affordable and pays; what is left from columns of
    ``H⁻¹`` (:func:`_columns_chi2`)."""
    edges, member = np.unique(np.concatenate(groups).astype(np.int64), return_inverse=True)
    members = np.split(member.ravel(), np.cumsum([len(g) for g in groups])[:-1])
    r, J, var, H = _whitened(solver, edges)
    out = np.full(len(groups), np.nan)
    if H is not None:
        large = [i for i, m in enumerate(members) if len(m) > LEFT_OUT_FROM]
        if large:
            out[large] = _left_out_chi2(H, r, J, var, [members[i] for i in large], sign)
        small = [i for i, m in enumerate(members) if len(m) <= LEFT_OUT_FROM]
        if small and _selected_pays(solver, len(np.unique(np.concatenate(
                [members[i] for i in small])))):
            out[small] = _selected_chi2(r, J, var, [members[i] for i in small], H, sign)
            if np.all(np.isnan(out[small])):
                _Unaffordable.mark(solver)
    rest = np.flatnonzero(np.isnan(out))
    if len(rest):
        out[rest] = _columns_chi2(r, J, var, [members[i] for i in rest], H, chunk, sign)
    return out


#: Groups of more edges than this are scored by :func:`_left_out_chi2` (one factorization),
#: not from ``H⁻¹``'s entries at every pair of their ends (intel's revisit of 195 closures:
#: 585 columns of ``H⁻¹``, or a selected inverse that fills in a dense 1,170² block).
LEFT_OUT_FROM = 32


def _left_out_chi2(H: sp.csc_matrix, r: Array, J: Array, var: np.ndarray,
                   members: list[np.ndarray], sign: float) -> Array:
    """The group χ² of each group (``members``: indices into the edges of whitened
    residuals ``r``, Jacobians ``J``, unknowns ``var``) by one solve (Woodbury's identity):
    with ``S = I + s J H⁻¹ Jᵀ``, ``rᵀ S⁻¹ r = rᵀr − s bᵀ (H + s JᵀJ)⁻¹ b``, ``b = Jᵀr``: the
    group left out of ``H`` (``s`` −1, deletion) or put in (``s`` +1, innovation). One
    symbolic analysis serves every group (``H``'s pattern holds theirs); ``nan`` where the
    changed matrix does not factor (the group alone holds some unknowns)."""
    parts = [_normal_block(r[m], J[m], var[m], H.shape[0]) for m in members]
    rows = np.concatenate([np.zeros(0, dtype=np.int64)] + [q[0] for q in parts])
    cols = np.concatenate([np.zeros(0, dtype=np.int64)] + [q[1] for q in parts])
    U = with_entries(H, np.stack([rows, cols], axis=1))
    factor = SPDFactor(U.indptr, U.indices)
    out = np.full(len(members), np.nan)
    for i, (block_rows, block_cols, values, b, rr) in enumerate(parts):
        data = U.data.copy()
        np.add.at(data, positions(U, block_rows, block_cols), sign * values)
        try:
            x = factor.solve(data, b)
        except np.linalg.LinAlgError:
            continue
        chi2 = rr - sign * float(b @ x)
        if np.isfinite(chi2) and chi2 >= 0.0:  # else an indefinite matrix "solved"
            out[i] = chi2
    return out


def _normal_block(r: Array, J: Array, var: np.ndarray, size: int
                  ) -> tuple[np.ndarray, np.ndarray, Array, Array, float]:
    """A group's ``JᵀJ`` over its unknowns as upper-triangle entries ``(rows, cols,
    values)`` (repeats summed where they are added), its ``b = Jᵀr`` of length ``size`` and
    ``rᵀr``."""
    held = var < 0
    inner = np.einsum("kpi,kpj->kij", J, J)  # each edge's JᵀJ over its 2p unknowns
    rows = np.broadcast_to(var[:, :, None], inner.shape)
    cols = np.broadcast_to(var[:, None, :], inner.shape)
    keep = ~held[:, :, None] & ~held[:, None, :] & (rows <= cols)
    b = np.zeros(size)
    np.add.at(b, var[~held], np.einsum("kpi,kp->ki", J, r)[~held])
    return rows[keep], cols[keep], inner[keep], b, float(np.sum(r * r))


def _columns_chi2(r: Array, J: Array, var: np.ndarray, members: list[np.ndarray],
                  H: sp.csc_matrix | None, chunk: int, sign: float) -> Array:
    """:func:`group_chi2` of the groups ``members`` (indices into the edges of ``r``, ``J``,
    ``var``) from columns of ``H⁻¹`` (upper triangle ``H``; ``None``: no unknowns).

    A group's columns of ``H⁻¹`` are its edges' own, so each edge is solved once for every
    group it is in: groups that share edges (a closure alone and its place, scored together
    by a settling round) are batched with them (:func:`_batches`)."""
    solve, unknowns = _split(H)
    out = np.zeros(len(members))
    for batch_edges, batch_groups in _batches(members, len(r), chunk):
        local = np.full(len(r), -1, dtype=np.int64)
        local[batch_edges] = np.arange(len(batch_edges))
        out[batch_groups] = _batch_chi2(
            r[batch_edges], J[batch_edges], var[batch_edges],
            [local[members[i]] for i in batch_groups], solve, unknowns, sign)
    return out


def _selected_pays(solver: H2OSolver, edges: int) -> bool:
    """Whether scoring ``edges`` edges from the selected inverse of the solver's ``H`` is
    cheaper than from their columns of ``H⁻¹`` (:data:`SELECTED_FROM`) and not known to be
    unaffordable (:class:`_Unaffordable`)."""
    return edges >= SELECTED_FROM and not _Unaffordable.holds(solver)


#: Fewest edges for which :func:`_group_chi2` scores from the selected inverse: about where
#: it costs what their columns of ``H⁻¹`` do (measured on intel, a 1,000-pose 3-D grid and
#: city10000: the same at 8-16 closures, 2-7 times faster at 128).
SELECTED_FROM = 16


class _Unaffordable:
    """The last solver (per thread) whose selected inverse was beyond
    :data:`~h2o_slam.core.selinv.MAX_WORK` or did not factor, by its size: weights change
    its pattern little, so its closures are scored from columns of ``H⁻¹`` without a
    factorization to learn it again."""

    _local = threading.local()

    @classmethod
    def _key(cls, solver: H2OSolver) -> tuple[int, int, int]:
        return id(solver), solver.num_nodes, solver.num_edges

    @classmethod
    def holds(cls, solver: H2OSolver) -> bool:
        return getattr(cls._local, "key", None) == cls._key(solver)

    @classmethod
    def mark(cls, solver: H2OSolver) -> None:
        cls._local.key = cls._key(solver)


def _selected(H: sp.csc_matrix, var: np.ndarray, members: list[np.ndarray]
              ) -> SelectedInverse | None:
    """The selected inverse of ``H`` (upper triangle) holding every entry the groups read:
    ``H``'s pattern widened by each group's pairs of end nodes (``None``: not affordable,
    or ``H`` does not factor)."""
    p = var.shape[1] // 2
    nodes = np.where(var[:, ::p] >= 0, var[:, ::p] // p, -1)  # each edge's two end nodes
    pairs = _node_pairs(nodes, members)
    within = np.stack(np.meshgrid(np.arange(p), np.arange(p), indexing="ij"), -1).reshape(-1, 2)
    return selected_inverse(H, (pairs[:, None, :] * p + within[None, :, :]).reshape(-1, 2))


def _node_pairs(nodes: np.ndarray, members: list[np.ndarray]) -> np.ndarray:
    """Every pair of free end ``nodes`` (``e × 2``, -1: held) of each group's edges, each
    node with itself too (a block of ``H`` may hold stored zeros that the factor leaves
    out): ``k × 2``, each pair once. Groups of one size at a time."""
    sizes = np.array([len(m) for m in members])
    out = [np.zeros((0, 2), dtype=np.int64)]
    for size in np.unique(sizes):
        ends = nodes[np.array([members[i] for i in np.flatnonzero(sizes == size)])]
        ends = ends.reshape(len(ends), 2 * size)
        i, j = np.triu_indices(2 * size)
        pairs = np.stack([ends[:, i], ends[:, j]], axis=-1).reshape(-1, 2)
        out.append(pairs[np.all(pairs >= 0, axis=1)])
    pairs = np.concatenate(out)
    # Unique as one integer key each (np.unique by rows sorts records: ten times slower).
    span = int(pairs.max(initial=0)) + 1
    key = np.unique(pairs[:, 0] * span + pairs[:, 1])
    return np.stack([key // span, key % span], axis=1)


def _selected_chi2(r: Array, J: Array, var: np.ndarray, members: list[np.ndarray],
                   H: sp.csc_matrix, sign: float) -> Array:
    """:func:`group_chi2` of each group (``members``: indices into the edges of ``r``,
    ``J``, ``var``) from the blocks of ``H⁻¹`` at its edges' ends (:func:`_selected`),
    groups of one size at a time: ``J_g Σ J_hᵀ`` for every pair of the group's edges;
    ``nan`` throughout where the selected inverse is not to be had."""
    out = np.full(len(members), np.nan)
    selected = _selected(H, var, members)
    if selected is None:
        return out
    p = r.shape[1]
    sizes = np.array([len(m) for m in members])
    for size in np.unique(sizes):
        which = np.flatnonzero(sizes == size)
        idx = np.array([members[i] for i in which], dtype=np.int64)  # (G, size)
        G = len(which)
        try:
            sigma = selected.blocks(var[idx].reshape(G, size * 2 * p))
        except KeyError:  # an entry the widened pattern should hold: the columns serve
            continue
        Jg = J[idx]  # (G, size, p, 2p)
        cov = np.einsum("gkij,gkjlm,glnm->gkiln", Jg,
                        sigma.reshape(G, size, 2 * p, size, 2 * p), Jg, optimize=True)
        S = np.eye(size * p) + sign * cov.reshape(G, size * p, size * p)
        out[which] = _quadratic_forms(S, r[idx].reshape(G, size * p))
    return out


def _batches(members: list[np.ndarray], count: int, chunk: int
             ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Groups (``members``: indices into ``count`` edges) packed into batches of at most
    ``chunk`` edges, groups that share an edge in one batch (a larger set of such groups
    is a batch of its own): each batch's edges and groups."""
    from scipy.sparse.csgraph import connected_components  # on use: see chdtri

    sizes = np.array([len(m) for m in members])
    rows = np.repeat(np.arange(len(members)), sizes)
    cols = np.concatenate(members) if len(members) else np.zeros(0, dtype=np.int64)
    # Edges and groups as one bipartite graph: its components are the sets to keep whole.
    total = count + len(members)
    link = sp.coo_matrix((np.ones(len(cols)), (cols, count + rows)), shape=(total, total))
    _, label = connected_components(link, directed=False)
    edge_label, group_label = label[:count], label[count:]
    order = np.argsort(edge_label, kind="stable")
    bounds = np.flatnonzero(np.diff(edge_label[order])) + 1
    batches: list[tuple[np.ndarray, np.ndarray]] = []
    current: list[np.ndarray] = []
    for component in np.split(order, bounds):
        if current and sum(map(len, current)) + len(component) > chunk:
            batches.append(_batch_of(current, edge_label, group_label))
            current = []
        current.append(component)
    if current:
        batches.append(_batch_of(current, edge_label, group_label))
    return batches


def _batch_of(components: list[np.ndarray], edge_label: np.ndarray, group_label: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """The edges of ``components`` and the groups with them."""
    edges = np.concatenate(components)
    return edges, np.flatnonzero(np.isin(group_label, edge_label[edges]))


def _batch_chi2(r: Array, J: Array, var: np.ndarray, groups: list[np.ndarray],
                solve: Split | None, unknowns: int, sign: float) -> Array:
    """:func:`group_chi2` of ``groups`` (indices into the batch's edges: ``r``, ``J``,
    ``var``), every one from the same columns of ``H⁻¹``: each group a super-edge, its
    edges' Jacobians block-diagonal."""
    p = r.shape[1]
    columns = None
    if solve is not None:
        try:
            columns = _map_columns(solve, J, var, unknowns)
        except np.linalg.LinAlgError:  # singular: a direction no edge constrains
            pass  # the edges' own covariance alone
    out = np.zeros(len(groups))
    sizes = np.array([len(g) for g in groups])
    for size in np.unique(sizes):
        which = np.flatnonzero(sizes == size)
        idx = np.array([groups[i] for i in which], dtype=np.int64)  # (G, size)
        rg = r[idx].reshape(len(which), size * p)
        S = np.broadcast_to(np.eye(size * p), (len(which), size * p, size * p)).copy()
        if columns is not None and size == 1:  # each edge's own block: no gathered copy
            Y, Z = columns
            S += sign * np.matmul(Y.transpose(1, 2, 0), Z.transpose(1, 0, 2))[idx[:, 0]]
        elif columns is not None:
            Y, Z = (c[:, idx, :].reshape(unknowns, len(which), size * p) for c in columns)
            S += sign * np.matmul(Y.transpose(1, 2, 0), Z.transpose(1, 0, 2))
        out[which] = _quadratic_forms(S, rg)
    return out


#: Side up to which a stack of joint covariances is solved at once (beyond it one by one,
#: by triangular solves).
BATCHED_UP_TO = 64


def _quadratic_forms(S: Array, r: Array) -> Array:
    """``rᵀ S⁺ r`` for each of the stacked symmetric positive semi-definite ``S``.

    The pseudo-inverse because ``I − JΣJᵀ`` of an edge the map cannot do without is
    singular; by Cholesky where ``S`` factors, since the pseudo-inverse's eigendecomposition
    costs ten times as much (smallGrid3D's place of 164 closures, 984 × 984: half of a
    robust solve's time; a 1,000-pose grid's 433 closures, 6 × 6 each: 20 ms). Where
    Cholesky succeeds the matrix is numerically positive definite and the two agree.
    """
    if S.shape[-1] <= BATCHED_UP_TO:
        try:
            y = np.linalg.solve(np.linalg.cholesky(S), r[..., None])[..., 0]
            return np.einsum("ei,ei->e", y, y)
        except np.linalg.LinAlgError:  # one of them singular: each alone
            pass
    from scipy.linalg import solve_triangular  # on use: see chdtri

    out = np.empty(len(S))
    for i, (Si, ri) in enumerate(zip(S, r, strict=True)):
        try:
            y = solve_triangular(np.linalg.cholesky(Si), ri, lower=True, check_finite=False)
            out[i] = y @ y
        except np.linalg.LinAlgError:
            out[i] = ri @ np.linalg.pinv(Si, hermitian=True) @ ri
    return out


def _whitened(solver: H2OSolver, edges: np.ndarray
              ) -> tuple[Array, Array, np.ndarray, sp.csc_matrix | None]:
    """Whitened residuals (e × p) and Jacobians on both ends (e × p × 2p) of ``edges``, the
    unknown of each Jacobian column (-1 where the system holds the end), and the upper
    triangle of the weighted Gauss–Newton matrix ``H`` (``None`` without unknowns)."""
    H, _, free_nodes = ExactSystem(solver).normal_equations()
    p = solver.p
    a, b = solver.a[edges], solver.b[edges]
    r, J = whitened_terms(solver, edges)
    block = np.full(solver.num_nodes + 1, -1, dtype=np.int64)  # [-1]: the earth, held
    block[free_nodes] = np.arange(len(free_nodes))
    ends = np.stack([block[a], block[b]], axis=1)
    var = np.where(ends[:, :, None] >= 0, ends[:, :, None] * p + np.arange(p), -1)
    var = var.reshape(len(edges), 2 * p)
    return r, J, var, upper(H) if H.shape[0] else None


def _split(U: sp.csc_matrix | None) -> tuple[Split | None, int]:
    """The split solve (:meth:`~h2o_slam.core.spd.SPDFactor.split_solve`) with the matrix
    whose upper triangle is ``U`` (``None`` without one), and its size."""
    if U is None:
        return None, 0
    factor = SPDFactor(U.indptr, U.indices)
    return (lambda B: factor.split_solve(U.data, B)), U.shape[0]


def _map_columns(split: Split, J: Array, var: np.ndarray, size: int) -> tuple[Array, Array]:
    """``(Y, Z)``, each ``(size, k, p)``, with ``Y[:, e]ᵀ Z[:, f] = J_e Σ J_fᵀ`` for the ``k``
    edges' whitened Jacobians ``J`` (``k × p × 2p``), ``Σ = H⁻¹`` over the unknowns ``var``
    of their columns (-1: held, 0): ``Jᵀ``'s columns scattered into the unknowns and split
    solved (:meth:`~h2o_slam.core.spd.SPDFactor.split_solve`). A quarter of the work of
    solving for the ``2p`` columns of ``H⁻¹`` at each edge's ends: ``p`` columns, half a
    solve each (city10000 with 1,000 false closures out: 86 % of a robust solve)."""
    k, rows, _ = J.shape
    e, u = np.nonzero(var >= 0)
    # Column-major, as the solver takes and gives it (no transposing copies).
    B = np.zeros((size, k * rows), order="F")
    for j in range(rows):
        # add, not assign: a self-loop's two ends are one unknown block (graphs and the
        # mapper refuse them, the solver's own API does not)
        np.add.at(B, (var[e, u], e * rows + j), J[e, j, u])
    Y, Z = split(B)
    return Y.reshape(size, k, rows), Z.reshape(size, k, rows)


def _binary(w: Array) -> bool:
    return bool(np.all((w <= WEIGHT_TOLERANCE) | (w >= 1.0 - WEIGHT_TOLERANCE)))
