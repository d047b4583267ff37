"""The pose tree (thesis 3.3.2): each pose is stored relative to its parent.

The earth is the root. It is not a node of the arrays: a node whose parent is
:data:`~h2o_slam.core.graph.EARTH` is the top of a subtree, and its local transform is its pose in
the world frame. An edge's *path* runs through the tree from ``a`` to ``b``; its *root* is the
path node of smallest depth (the lowest common ancestor, possibly the earth); its *domain* is
the path without the root — the nodes whose local transforms change the edge's error.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.capacity import ArrayRef, ensure
from h2o_slam.core.compiled import kernel
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import EARTH, EdgeKind, PoseGraph


@dataclass(frozen=True)
class EdgePath:
    """The tree path of one edge.

    Attributes:
        root: the lowest common ancestor of ``a`` and ``b`` (:data:`EARTH` possibly).
        a_chain: nodes from just below the root down to ``a`` (empty when ``a`` is the root).
        b_chain: nodes from just below the root down to ``b``.
    """

    root: int
    a_chain: np.ndarray
    b_chain: np.ndarray

    @cached_property
    def domain(self) -> np.ndarray:
        """The nodes whose local transforms change the edge's error: both chains."""
        return np.concatenate([self.a_chain, self.b_chain])


class PoseTree:
    """Parent pointers, depths and local transforms of ``n`` nodes under the earth.

    ``R[i], t[i]`` map node ``i``'s frame into its parent's frame. Depth of a top node is 1
    (the earth has depth 0).
    """

    def __init__(self, capacity: int = 16) -> None:
        self.n = 0
        self.parent = np.full(capacity, EARTH, dtype=np.int64)
        self.depth = np.zeros(capacity, dtype=np.int64)
        self.R = np.tile(np.eye(3), (capacity, 1, 1))
        self.t = np.zeros((capacity, 3))
        self._children: list[set[int]] | None = None

    # -- growth -------------------------------------------------------------------------------

    def add_node(self, parent: int, R_local: Array, t_local: Array) -> int:
        """Append a node under ``parent`` (:data:`EARTH` for a new top) and return its index."""
        ensure(self.arrays(), self.n + 1)
        i = self.n
        self.parent[i] = parent
        self.depth[i] = 1 if parent == EARTH else self.depth[parent] + 1
        self.R[i] = R_local
        self.t[i] = t_local
        self.n += 1
        if self._children is not None:
            self._children.append(set())
            if parent != EARTH:
                self._children[parent].add(i)
        return i

    def children(self, node: int) -> set[int]:
        """Children of ``node`` (built on first use, then maintained)."""
        if self._children is None:
            kids: list[set[int]] = [set() for _ in range(self.n)]
            for child, parent in enumerate(self.parent[: self.n]):
                if parent != EARTH:
                    kids[int(parent)].add(child)
            self._children = kids
        return self._children[node]

    def subtree(self, node: int) -> list[int]:
        """``node`` and all its descendants, parents before children."""
        out = [node]
        i = 0
        while i < len(out):
            out.extend(self.children(out[i]))
            i += 1
        return out

    def subtree_exceeds(self, node: int, limit: int) -> bool:
        """Whether ``node``'s subtree has more than ``limit`` nodes (stops counting there)."""
        todo = [node]
        count = 0
        while todo:
            count += 1
            if count > limit:
                return True
            todo.extend(self.children(todo.pop()))
        return False

    def reparent(self, node: int, parent: int, R_local: Array, t_local: Array) -> list[int]:
        """Hang ``node`` (with its subtree) under ``parent`` with a new local transform.

        Returns the subtree, whose depths are updated.

        Raises:
            ValueError: ``parent`` is ``node`` or one of its descendants.
        """
        sub = self.subtree(node)
        if parent in sub:
            raise ValueError(f"cannot hang node {node} under its own descendant {parent}")
        old = int(self.parent[node])
        if old != EARTH:
            self.children(old).discard(node)
        if parent != EARTH:
            self.children(parent).add(node)
        self.parent[node] = parent
        self.R[node] = R_local
        self.t[node] = t_local
        shift = (1 if parent == EARTH else int(self.depth[parent]) + 1) - int(self.depth[node])
        self.depth[sub] += shift
        return sub

    def arrays(self) -> list[ArrayRef]:
        """The per-node arrays as ``(owner, name, fill)`` (:mod:`h2o_slam.core.capacity`)."""
        return [(self, "parent", EARTH), (self, "depth", 0), (self, "R", np.eye(3)),
                (self, "t", 0.0)]

    @classmethod
    def from_parents(cls, parent: np.ndarray, R_world: Array, t_world: Array) -> PoseTree:
        """A tree with the given parent pointers and local transforms that reproduce the world
        poses ``(R_world, t_world)``.

        Raises:
            ValueError: the parent pointers contain a cycle.
        """
        top = parent == EARTH
        p = np.where(top, 0, parent)
        R_loc, t_loc = geo.between(R_world[p], t_world[p], R_world, t_world)
        # Renormalized: world poses composed down a deep tree carry rounding of every level,
        # and a tree rebuilt from them again and again (each exact solve's seed) compounds it.
        return cls.from_local(parent, geo.renormalize(np.where(top[:, None, None], R_world,
                                                               R_loc)),
                              np.where(top[:, None], t_world, t_loc))

    @classmethod
    def from_local(cls, parent: np.ndarray, R_local: Array, t_local: Array) -> PoseTree:
        """A tree with the given parent pointers and local transforms (copied).

        Raises:
            ValueError: the parent pointers contain a cycle.
        """
        n = len(parent)
        tree = cls(capacity=max(n, 1))
        tree.n = n
        tree.parent[:n] = parent
        tree.depth[:n] = depths(np.asarray(parent))
        tree.R[:n] = R_local
        tree.t[:n] = t_local
        return tree

    # -- queries ------------------------------------------------------------------------------

    def path(self, a: int, b: int) -> EdgePath:
        """The tree path between ``a`` and ``b`` (``a`` may be :data:`EARTH`)."""
        root, a_chain, b_chain = _path(self.parent, self.depth, a, b)
        return EdgePath(int(root), a_chain, b_chain)

    def top(self, node: int) -> int:
        """The top of ``node``'s subtree (its ancestor just below the earth)."""
        return int(_top(self.parent, node))

    def chain_poses(self, chain: np.ndarray) -> tuple[Array, Array]:
        """Poses of the chain's nodes in the frame of the first node's parent."""
        return geo.cumulative_compose(self.R[chain], self.t[chain])

    def chain_end(self, chain: np.ndarray) -> tuple[Array, Array]:
        """Pose of the chain's last node in the frame of the first node's parent (the last
        row of :meth:`chain_poses`, compiled: an edge's residual walks its whole tree path)."""
        R, t = np.empty((3, 3)), np.empty(3)
        _compose_chain(self.R, self.t, np.ascontiguousarray(chain, dtype=np.int64), R, t)
        return R, t

    def world_pose(self, node: int) -> tuple[Array, Array]:
        """World pose of one node, composed down its ancestry (O(depth), compiled)."""
        return self.chain_end(self.path(EARTH, node).b_chain)

    def world_poses(self) -> tuple[Array, Array]:
        """World poses of all nodes, composed from the earth down (parents first)."""
        n = self.n
        return compose_down(self.parent[:n], self.top_down(), self.R[:n], self.t[:n])

    def compose_below(self, R: Array, t: Array, first: int) -> None:
        """Complete world poses ``(R, t)`` whose first ``first`` entries are given: every
        node from ``first`` on is composed under its parent's pose in ``(R, t)``."""
        n = self.n
        order = self.top_down()
        _compose_down(self.parent[:n], order[order >= first], self.R[:n], self.t[:n], R, t)

    def top_down(self) -> np.ndarray:
        """Node indices ordered by depth: every parent comes before its children."""
        return np.argsort(self.depth[: self.n], kind="stable")

    def set_world_poses(self, R_world: Array, t_world: Array) -> None:
        """Set every local transform so that the world poses become ``(R_world, t_world)``."""
        n = self.n
        _set_local(self.parent[:n], np.ascontiguousarray(R_world, dtype=float),
                   np.ascontiguousarray(t_world, dtype=float), self.R, self.t)

    def tops(self) -> np.ndarray:
        """The top of each node's subtree (its ancestor just below the earth)."""
        top = np.arange(self.n)
        _tops_down(self.parent[: self.n], self.top_down(), top)
        return top


def compose_down(parent: np.ndarray, order: np.ndarray, R_local: Array, t_local: Array
                 ) -> tuple[Array, Array]:
    """World poses from local transforms, composed in ``order`` (parents before children,
    e.g. :meth:`PoseTree.top_down`)."""
    R, t = np.empty_like(R_local), np.empty_like(t_local)
    _compose_down(parent, order, R_local, t_local, R, t)
    return R, t


# Compiled: composing level by level ran one numpy call per level, O(depth) interpreter
# steps (40 ms on a 20,000-node chain); these are one pass over the nodes.

@kernel
def _compose_down(parent: np.ndarray, order: np.ndarray, R_loc: Array, t_loc: Array,
                  R: Array, t: Array) -> None:
    for i in order:
        p = parent[i]
        if p == EARTH:
            R[i] = R_loc[i]
            t[i] = t_loc[i]
        else:
            geo.mul3_into(R[p], R_loc[i], R[i])
            t[i] = t[p]
            geo.add_mulv3(R[p], t_loc[i], t[i])


# Compiled: walking up a deep tree one interpreter step per level cost a new loop closure
# 1-2 ms on city10000 while the tree was a 5,000-node chain (no exact solve merged yet).

@kernel
def _path(parent: np.ndarray, depth: np.ndarray, a: int, b: int
          ) -> tuple[int, np.ndarray, np.ndarray]:
    da = 0 if a == EARTH else depth[a]
    db = depth[b]
    up_a = np.empty(da, dtype=np.int64)
    up_b = np.empty(db, dtype=np.int64)
    na = 0
    nb = 0
    while db > da:
        up_b[nb] = b
        nb += 1
        b = parent[b]
        db -= 1
    while da > db:
        up_a[na] = a
        na += 1
        a = parent[a]
        da -= 1
    while a != b:
        up_a[na] = a
        up_b[nb] = b
        na += 1
        nb += 1
        a = parent[a]
        b = parent[b]
    return a, up_a[:na][::-1].copy(), up_b[:nb][::-1].copy()


@kernel
def _top(parent: np.ndarray, node: int) -> int:
    while parent[node] != EARTH:
        node = parent[node]
    return node


@kernel
def _compose_chain(R_loc: Array, t_loc: Array, chain: np.ndarray, R: Array, t: Array) -> None:
    R[:] = np.eye(3)
    t[:] = 0.0
    tmp = np.empty((3, 3))
    for i in chain:
        geo.add_mulv3(R, t_loc[i], t)
        geo.mul3_into(R, R_loc[i], tmp)
        R[:] = tmp


@kernel
def _set_local(parent: np.ndarray, R_world: Array, t_world: Array, R: Array, t: Array) -> None:
    """Local transforms ``(R, t)`` of every node under its parent from world poses; each
    local rotation renormalized (:func:`~h2o_slam.core.geometry.renormalize`)."""
    loc = np.empty((3, 3))
    for i in range(len(parent)):
        p = parent[i]
        if p == EARTH:
            geo.renormalize_into(R_world[i], R[i])
            t[i] = t_world[i]
        else:
            geo.mul3t_into(R_world[p], R_world[i], loc)
            geo.renormalize_into(loc, R[i])
            t[i] = geo.mulv3t(R_world[p], t_world[i] - t_world[p])


@kernel
def _tops_down(parent: np.ndarray, order: np.ndarray, top: np.ndarray) -> None:
    for i in order:
        if parent[i] != EARTH:
            top[i] = top[parent[i]]


@kernel
def _depths_into(parent: np.ndarray, depth: np.ndarray) -> bool:
    """Fill ``depth`` (zeros on entry); False on a cycle or an unknown parent."""
    n = len(parent)
    walk = np.empty(n, dtype=np.int64)
    for i in range(n):
        k, j, base = 0, i, 0
        while j != EARTH and depth[j] == 0:
            if j < 0 or j >= n or k == n:
                return False
            walk[k] = j
            k += 1
            j = parent[j]
        if j != EARTH:
            base = depth[j]
        for s in range(k - 1, -1, -1):
            base += 1
            depth[walk[s]] = base
    return True


def depths(parent: np.ndarray) -> np.ndarray:
    """Depth of every node of a forest of parent pointers (a top has depth 1).

    Raises:
        ValueError: the parent pointers contain a cycle or an unknown parent.
    """
    depth = np.zeros(len(parent), dtype=np.int64)
    if not _depths_into(np.ascontiguousarray(parent, dtype=np.int64), depth):
        raise ValueError("parent pointers contain a cycle or an unknown parent")
    return depth


def tree_edges(graph: PoseGraph, parents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each node, the relative edge joining it to its parent (-1 for none) and whether
    it points parent → node. Of several, the first forward edge wins, else the first
    reversed one: one choice for everything that concatenates tree edges."""
    n = graph.num_nodes
    edge = np.full(n, -1, dtype=np.int64)
    forward = np.ones(n, dtype=bool)
    rel = np.flatnonzero(graph.kind == EdgeKind.RELATIVE)
    a, b = graph.a[rel], graph.b[rel]
    up = (parents[a] == b) & (parents[b] != a)
    down = parents[b] == a
    # Assigned in reverse so that the first of several edges is the one that stays, and the
    # forward ones last so that they win over reversed ones.
    edge[a[up][::-1]] = rel[up][::-1]
    forward[a[up]] = False
    edge[b[down][::-1]] = rel[down][::-1]
    forward[b[down]] = True
    return edge, forward


def spanning_parents(
    num_nodes: int, a: np.ndarray, b: np.ndarray, roots: list[int] | None = None
) -> np.ndarray:
    """Parent pointers of a breadth-first spanning forest of the graph with edges ``(a, b)``.

    Breadth-first keeps the tree shallow, which bounds the path length of every edge.
    Each connected component hangs from the earth at its first node (or at ``roots``).
    Only relative edges should be passed: GPS edges make poor tree edges (thesis 3.3.10).
    """
    # Adjacency in CSR form, each node's neighbours in the order scipy's undirected
    # breadth-first search visits them (edges out of it by target, then edges into it by
    # source), so that the forest does not depend on which implementation built it.
    a = np.asarray(a, dtype=np.int64)
    b = np.asarray(b, dtype=np.int64)
    ends = np.concatenate([a, b])
    others = np.concatenate([b, a])
    incoming = np.repeat([0, 1], len(a))
    order = np.lexsort((others, incoming, ends))
    first = np.searchsorted(ends[order], np.arange(num_nodes + 1))
    parent = np.full(num_nodes, -2, dtype=np.int64)
    _breadth_first_forest(first, others[order], np.asarray(roots or [], dtype=np.int64),
                          parent)
    return parent


@kernel
def _breadth_first_forest(first: np.ndarray, neighbours: np.ndarray, roots: np.ndarray,
                          parent: np.ndarray) -> None:
    """Breadth-first trees from each root, then from each node still unreached (``parent``
    -2), in index order; a tree's start hangs from the earth."""
    queue = np.empty(len(parent), dtype=np.int64)
    for i in range(len(roots) + len(parent)):
        s = roots[i] if i < len(roots) else i - len(roots)
        if parent[s] != -2:
            continue
        parent[s] = EARTH
        queue[0] = s
        head, tail = 0, 1
        while head < tail:
            node = queue[head]
            head += 1
            for k in range(first[node], first[node + 1]):
                other = neighbours[k]
                if parent[other] == -2:
                    parent[other] = node
                    queue[tail] = other
                    tail += 1
