"""The pose tree (thesis 3.3.1): world poses and trees rebuilt from them."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order

from h2o_slam.core import geometry as geo
from h2o_slam.core.tree import EARTH, PoseTree, spanning_parents


def _orthonormality_error(R: np.ndarray) -> float:
    return float(np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max())


def test_trees_rebuilt_from_their_world_poses_stay_rotations() -> None:
    # Every exact solve seeds its tree from the last solution's world poses: on a deep
    # chain the rounding of each level compounded to NaN within 30 rebuilds.
    rng = np.random.default_rng(3)
    n = 20000
    parent = np.arange(n) - 1
    parent[0] = EARTH
    tree = PoseTree.from_local(parent, geo.so3_exp(rng.normal(size=(n, 3))),
                               rng.normal(size=(n, 3)))
    for _ in range(30):
        tree = PoseTree.from_parents(parent, *tree.world_poses())
    R, t = tree.world_poses()
    assert np.all(np.isfinite(t))
    assert _orthonormality_error(R) < 1e-9


def test_the_tree_start_and_the_solver_choose_the_same_tree_edges() -> None:
    # Node 2 hangs from node 1 by two parallel forward edges and one reversed edge that
    # disagree: whichever is chosen, the start must satisfy the edge the solver calls the
    # tree edge (once, two functions broke such ties opposite ways).
    from h2o_slam.core.graph import EdgeKind, edge_chi2, make_graph
    from h2o_slam.core.modes import build_solver

    yaw = [geo.yaw_to_matrix(np.array(v)) for v in (0.0, 0.1, 0.3, -0.2)]
    steps = np.array([[1.0, 0, 0], [1.0, 0, 0], [1.5, 0.2, 0], [-0.9, 0.1, 0]])
    kind = np.full(4, EdgeKind.RELATIVE, dtype=np.int8)
    graph = make_graph(True, np.arange(3), np.tile(np.eye(3), (3, 1, 1)), np.zeros((3, 3)),
                       kind, np.array([0, 1, 1, 2]), np.array([1, 2, 2, 1]),
                       np.stack(yaw), steps, np.tile(np.eye(6), (4, 1, 1)))
    solver, start = build_solver(graph, init="tree")
    chosen = solver.tree_edge[[1, 2]]
    assert chosen.tolist() == [0, 1]  # the first forward edge of each node
    assert np.allclose(edge_chi2(start)[chosen], 0.0, atol=1e-20)
    assert edge_chi2(start)[[2, 3]].min() > 1e-3


def test_one_world_pose_is_the_composition_of_its_ancestry() -> None:
    rng = np.random.default_rng(7)
    n = 300
    parent = np.array([EARTH] + [int(rng.integers(0, k)) for k in range(1, n)])
    tree = PoseTree.from_local(parent, geo.so3_exp(rng.normal(size=(n, 3))),
                               rng.normal(size=(n, 3)))
    R_all, t_all = tree.world_poses()
    for node in (0, 1, n // 2, n - 1):
        R, t = tree.world_pose(node)
        np.testing.assert_allclose(R, R_all[node], atol=1e-12)
        np.testing.assert_allclose(t, t_all[node], atol=1e-12)


def _scipy_forest(n, a, b, roots):
    """The breadth-first forest scipy's undirected search gives, start by start."""
    adj = coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n)).tocsr()
    parent = np.full(n, -2, dtype=np.int64)
    for s in list(roots) + list(range(n)):
        if parent[s] == -2:
            order, pred = breadth_first_order(adj, s, directed=False, return_predecessors=True)
            parent[order] = pred[order]
            parent[s] = EARTH
    return parent


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_spanning_forest_is_scipys_breadth_first_forest(data):
    """Same parents as scipy's search (so the tree start does not depend on which built it),
    on graphs with repeated edges, self-loops, isolated nodes and given roots."""
    n = data.draw(st.integers(1, 30))
    pairs = data.draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)),
                               max_size=60))
    roots = data.draw(st.lists(st.integers(0, n - 1), max_size=3, unique=True))
    a = np.array([p[0] for p in pairs], dtype=np.int64)
    b = np.array([p[1] for p in pairs], dtype=np.int64)
    parent = spanning_parents(n, a, b, roots)
    np.testing.assert_array_equal(parent, _scipy_forest(n, a, b, roots))
    assert not roots or parent[roots[0]] == EARTH  # later roots may lie in its tree
    assert np.all((parent >= EARTH) & (parent < n))


def _ancestry(parent, node):
    """``node`` and its ancestors up to its top, nearest first (EARTH excluded)."""
    out = []
    while node != EARTH:
        out.append(int(node))
        node = parent[node]
    return out


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_a_path_runs_from_the_lowest_common_ancestor_down_to_each_end(data):
    """Against the ancestry lists, on forests (several tops) and with the earth as one end."""
    n = data.draw(st.integers(1, 40))
    parent = np.array([EARTH if k == 0 or data.draw(st.booleans()) and k % 7 == 0
                       else data.draw(st.integers(0, k - 1)) for k in range(n)])
    tree = PoseTree.from_local(parent, np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)))
    b = data.draw(st.integers(0, n - 1))
    a = data.draw(st.sampled_from([EARTH, *range(n)]))
    up_a = [] if a == EARTH else _ancestry(parent, a)
    up_b = _ancestry(parent, b)
    common = [node for node in up_a if node in up_b]
    root = common[0] if common else EARTH
    path = tree.path(a, b)
    assert path.root == root
    np.testing.assert_array_equal(path.a_chain, up_a[: up_a.index(root)][::-1]
                                  if root in up_a else up_a[::-1])
    np.testing.assert_array_equal(path.b_chain, up_b[: up_b.index(root)][::-1]
                                  if root in up_b else up_b[::-1])
    assert tree.top(b) == up_b[-1]
    assert tree.top(b) == tree.tops()[b]


def test_a_chains_end_is_the_last_of_its_poses() -> None:
    """The compiled end pose against the cumulative composition, on a deep random chain."""
    rng = np.random.default_rng(3)
    n = 500
    parent = np.arange(-1, n - 1)
    tree = PoseTree.from_local(parent, geo.so3_exp(rng.normal(size=(n, 3))),
                               rng.normal(size=(n, 3)))
    for chain in (np.arange(n), np.arange(40, 300), np.array([7])):
        R_all, t_all = tree.chain_poses(chain)
        R, t = tree.chain_end(chain)
        np.testing.assert_allclose(R, R_all[-1], atol=1e-10)
        np.testing.assert_allclose(t, t_all[-1], atol=1e-9)
