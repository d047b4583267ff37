"""Reading and writing pose graphs in the g2o text format.

One line per element, fields separated by white space; blank lines and ``#`` comments
are ignored. Tags understood (the names g2o itself registers in ``types_slam2d.cpp`` and
``types_slam3d.cpp``):

Planar graphs (poses ``x y theta``, angles in rad; information in the order x, y, theta):

* ``VERTEX_SE2 id x y theta``
* ``EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33`` — relative pose of ``j`` in the
  frame of ``i``, upper triangle of its 3×3 information matrix.
* ``EDGE_PRIOR_SE2_XY id x y I11 I12 I22`` — GPS: world position of ``id`` (g2o's
  ``EdgeSE2XYPrior``).
* ``EDGE_PRIOR_SE2 id x y theta I11 .. I33`` — g2o's full SE(2) prior (``EdgeSE2Prior``),
  accepted only as an orientation prior: every information entry on x or y must be zero.

3-D graphs (positions in m, quaternions scalar-last ``qx qy qz qw``, information in the
order x, y, z, rot x, rot y, rot z, upper triangle row by row):

* ``VERTEX_SE3:QUAT id x y z qx qy qz qw``
* ``EDGE_SE3:QUAT i j x y z qx qy qz qw I11 .. I66`` (21 values).
* ``EDGE_SE3_XYZ_PRIOR id pid x y z I11 .. I33`` (6 values) — GPS: world position of
  ``id`` (g2o's ``EdgeSE3XYZPrior``).
* ``EDGE_SE3_PRIOR id pid x y z qx qy qz qw I11 .. I66`` — g2o's full SE(3) prior,
  accepted only as an orientation prior (information rows x, y, z all zero).
* ``PARAMS_SE3OFFSET pid x y z qx qy qz qw`` — the sensor offset the two g2o prior edges
  refer to by ``pid``. Only the identity offset is supported; the writer emits
  ``PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1`` so that g2o itself can load the file.

The rotational block of ``EDGE_SE3:QUAT`` (and ``EDGE_SE3_PRIOR``) information is taken
as information on the rotation-vector error ``Log(R_E)``, as GTSAM's ``readG2o`` does.
g2o's own ``EdgeSE3`` applies it to the quaternion's vector part, about half the angle,
so χ² values differ from g2o's by that convention (not from GTSAM's).

An information matrix must be positive semi-definite in the coordinates its edge constrains
(checked scaled by its largest entry, to 1e-6 of it); an indefinite one is an error, a
singular one is eigen-clamped as the graph is built (:func:`~h2o_slam.core.graph.make_graph`).

``FIX id ...`` lines are accepted and ignored: in g2o they anchor the gauge freedom, which
the solvers of this package fix themselves (earth node / first pose); fixing further poses
is not part of the model.

Node ids may be any non-negative integers. ``graph.ids`` is the sorted union of the ids
of vertices and edges, and every array indexes nodes by their position in it. A file
without ``VERTEX`` lines starts from :func:`~h2o_slam.core.graph.odometry_chain`.

Every bad line raises :class:`~h2o_slam.core.errors.G2OFormatError` naming the file, the line
(1-based; 0 for the file as a whole) and the reason.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.errors import G2OFormatError, InputError
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import EARTH, KIND_ROWS, EdgeKind, PoseGraph, make_graph, odometry_chain

PathLike = str | os.PathLike[str]

_PLANAR_ROWS = np.array([0, 1, 5])
_XY_ROWS = np.array([0, 1])
_XYZ_ROWS = np.arange(3)
_ALL_ROWS = np.arange(6)
# Below this norm a quaternion carries no rotation (same threshold as geometry).
_MIN_QUAT_NORM = 1e-12
# How many ulps around atan2 the writer searches for an angle that reproduces R exactly.
_YAW_ULPS = 4
# Negative eigenvalues of an information matrix scaled by its largest entry down to this are
# rounding of a semi-definite matrix written as text (the nodes' covariance tolerance).
_INFO_PSD_RTOL = 1e-6


@dataclass(frozen=True)
class _Tag:
    planar: bool
    n_int: int
    n_float: int


_TAGS = {
    "VERTEX_SE2": _Tag(True, 1, 3),
    "EDGE_SE2": _Tag(True, 2, 3 + 6),
    "EDGE_PRIOR_SE2_XY": _Tag(True, 1, 2 + 3),
    "EDGE_PRIOR_SE2": _Tag(True, 1, 3 + 6),
    "VERTEX_SE3:QUAT": _Tag(False, 1, 7),
    "EDGE_SE3:QUAT": _Tag(False, 2, 7 + 21),
    "EDGE_SE3_XYZ_PRIOR": _Tag(False, 2, 3 + 6),
    "EDGE_SE3_PRIOR": _Tag(False, 2, 7 + 21),
    "PARAMS_SE3OFFSET": _Tag(False, 1, 7),
}
_VERTEX_TAGS = ("VERTEX_SE2", "VERTEX_SE3:QUAT")


class _Problems:
    """Keeps the earliest offending line of a pass over several tag groups."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.first: tuple[int, str] | None = None

    def add(self, line: int, reason: str) -> None:
        if self.first is None or line < self.first[0]:
            self.first = (line, reason)

    def add_first(
        self, mask: np.ndarray, lines: np.ndarray, reason: str | Callable[[int], str]
    ) -> None:
        """Record the first row of ``mask``; ``reason`` is a string or ``row -> str``."""
        if np.any(mask):
            k = int(np.argmax(mask))
            self.add(int(lines[k]), reason if isinstance(reason, str) else reason(k))

    def raise_first(self) -> None:
        if self.first is not None:
            raise G2OFormatError(self.path, *self.first)


@dataclass
class _Group:
    tag: str
    lines: np.ndarray  # (n,) 1-based line numbers
    ints: np.ndarray  # (n, n_int) int64
    vals: Array  # (n, n_float)


@dataclass
class _Edges:
    lines: np.ndarray
    kind: np.ndarray
    a_id: np.ndarray  # external ids; EARTH for global edges
    b_id: np.ndarray
    meas_R: Array
    meas_t: Array
    info: Array


def read_g2o(path: PathLike) -> PoseGraph:
    """Read a pose graph from a g2o file (format in the module docstring).

    Returns:
        The graph; its estimate is the file's vertices, or the odometry chain when the file
        has no ``VERTEX`` lines.

    Raises:
        G2OFormatError: a line cannot be used (the message names file, line and reason).
        OSError: the file cannot be read.
    """
    return parse_g2o(os.fspath(path), Path(path).read_bytes())


def parse_g2o(name: str, data: bytes) -> PoseGraph:
    """:func:`read_g2o` of a file's bytes already read (``name`` is used in messages).

    Raises:
        G2OFormatError: as :func:`read_g2o`.
    """
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        line = data.count(b"\n", 0, err.start) + 1
        raise G2OFormatError(name, line, "not UTF-8 text") from None
    planar, raw = _split_lines(name, text)
    problems = _Problems(name)
    groups = {tag: _convert(problems, tag, *rows) for tag, rows in raw.items()}
    problems.raise_first()
    return _build(name, planar, groups)


def _split_lines(
    name: str, text: str
) -> tuple[bool, dict[str, tuple[list[int], list[list[str]]]]]:
    # The per-line work is kept to a split and a few look-ups; numbers are converted per
    # tag group with numpy afterwards, which is what keeps 30k-line files well under 1 s.
    raw: dict[str, tuple[list[int], list[list[str]]]] = {}
    planar: bool | None = None
    family_line = 0
    data_lines = 0
    for no, line in enumerate(text.split("\n"), 1):
        if "#" in line:
            line = line[: line.index("#")]
        fields = line.split()
        if not fields:
            continue
        data_lines += 1
        tag = fields[0]
        spec = _TAGS.get(tag)
        if spec is None:
            if tag == "FIX":
                _check_fix(name, no, fields)
                continue
            raise G2OFormatError(name, no, f"unknown tag {tag!r}")
        want = spec.n_int + spec.n_float
        if len(fields) - 1 != want:
            raise G2OFormatError(
                name, no, f"{tag} takes {want} fields after the tag, found {len(fields) - 1}"
            )
        if spec.planar != planar:
            if planar is None:
                planar, family_line = spec.planar, no
            else:
                kinds = ("3-D", "planar") if planar else ("planar", "3-D")
                raise G2OFormatError(
                    name, no, f"{kinds[0]} tag {tag} in a file that line {family_line} "
                    f"made {kinds[1]}; planar and 3-D tags cannot be mixed"
                )
        entry = raw.get(tag)
        if entry is None:
            entry = raw[tag] = ([], [])
        entry[0].append(no)
        entry[1].append(fields)
    if data_lines == 0:
        raise G2OFormatError(name, 0, "empty file: no vertices and no edges")
    if not any(tag.startswith("EDGE") for tag in raw):
        raise G2OFormatError(name, 0, "no edges")
    return bool(planar), raw


def _check_fix(name: str, no: int, fields: list[str]) -> None:
    if len(fields) < 2:
        raise G2OFormatError(name, no, "FIX takes at least one node id")
    for field in fields[1:]:
        if not _is_int(field) or int(field) < 0:
            raise G2OFormatError(name, no, f"FIX: {field!r} is not a non-negative integer id")


def _is_int(field: str) -> bool:
    try:
        np.array([field]).astype(np.int64)
    except (ValueError, OverflowError):
        return False
    return True


def _is_float(field: str) -> bool:
    try:
        np.array([field]).astype(np.float64)
    except ValueError:
        return False
    return True


def _convert(
    problems: _Problems, tag: str, lines_list: list[int], rows: list[list[str]]
) -> _Group:
    spec = _TAGS[tag]
    lines = np.array(lines_list, dtype=np.int64)
    arr = np.array(rows)
    int_part = arr[:, 1 : 1 + spec.n_int]
    val_part = arr[:, 1 + spec.n_int :]
    try:
        ints = int_part.astype(np.int64)
    except (ValueError, OverflowError):
        ints = np.zeros(int_part.shape, dtype=np.int64)
        _locate(problems, tag, lines, int_part, _is_int, "is not an integer id")
    try:
        vals = val_part.astype(np.float64)
    except ValueError:
        vals = np.zeros(val_part.shape)
        _locate(problems, tag, lines, val_part, _is_float, "is not a number")
    problems.add_first(np.any(ints < 0, axis=1), lines, f"{tag}: negative id")
    problems.add_first(
        ~np.all(np.isfinite(vals), axis=1), lines, f"{tag}: non-finite value (nan or inf)"
    )
    return _Group(tag, lines, ints, vals)


def _locate(
    problems: _Problems, tag: str, lines: np.ndarray, cols: np.ndarray,
    ok: Callable[[str], bool], what: str,
) -> None:
    # Only on the error path: find the first field that numpy refused, row by row.
    for k in range(len(cols)):
        for field in cols[k]:
            if not ok(str(field)):
                problems.add(int(lines[k]), f"{tag}: {str(field)!r} {what}")
                return


def _sym_from_upper(vals: Array, n: int) -> Array:
    """Symmetric ``(m, n, n)`` matrices from their row-major upper triangles ``(m, n(n+1)/2)``."""
    out = np.zeros((len(vals), n, n))
    iu, ju = np.triu_indices(n)
    out[:, iu, ju] = vals
    out[:, ju, iu] = vals
    return out


def _embed(block: Array, rows: np.ndarray) -> Array:
    out = np.zeros((len(block), 6, 6))
    out[:, rows[:, None], rows[None, :]] = block
    return out


def _quat(problems: _Problems, group: _Group, q: Array) -> Array:
    """Rotation matrices of quaternions ``(m, 4)``, reporting zero quaternions."""
    norm = np.linalg.norm(q, axis=1)
    bad = norm < _MIN_QUAT_NORM
    problems.add_first(bad, group.lines, f"{group.tag}: zero quaternion")
    return geo.quat_to_matrix(np.where(bad[:, None], [0.0, 0.0, 0.0, 1.0], q))


def _build(name: str, planar: bool, groups: dict[str, _Group]) -> PoseGraph:
    problems = _Problems(name)
    vertex = next((groups[t] for t in _VERTEX_TAGS if t in groups), None)
    params = groups.get("PARAMS_SE3OFFSET")
    _check_params(problems, params)
    edges = [
        _edges_of(problems, g, params) for t, g in groups.items() if t.startswith("EDGE")
    ]
    names = [f.name for f in fields(_Edges)]
    e = _Edges(*(np.concatenate([getattr(x, f) for x in edges]) for f in names))
    order = np.argsort(e.lines, kind="stable")
    e = _Edges(*(getattr(e, f)[order] for f in names))

    if vertex is not None:
        v_ids = vertex.ints[:, 0]
        _check_duplicates(problems, vertex, v_ids)
        a_ok = (e.kind != EdgeKind.RELATIVE) | np.isin(e.a_id, v_ids)
        b_ok = np.isin(e.b_id, v_ids)

        def missing(k: int) -> str:
            node = e.b_id[k] if a_ok[k] else e.a_id[k]
            return (f"edge uses node {node}, which has no VERTEX line (a file with vertices "
                    "needs one for every node)")

        problems.add_first(~(a_ok & b_ok), e.lines, missing)
        R_v, t_v = _vertex_poses(problems, vertex)
    _check_semi_definite(problems, e, planar)
    problems.raise_first()

    if vertex is not None:
        ids = np.unique(v_ids)
        R = np.empty((len(ids), 3, 3))
        t = np.empty((len(ids), 3))
        pos = np.searchsorted(ids, v_ids)
        R[pos], t[pos] = R_v, t_v
    else:
        rel = e.kind == EdgeKind.RELATIVE
        ids = np.union1d(e.a_id[rel], e.b_id)
        R = np.broadcast_to(np.eye(3), (len(ids), 3, 3)).copy()
        t = np.zeros((len(ids), 3))

    a = np.where(e.kind == EdgeKind.RELATIVE, np.searchsorted(ids, e.a_id), EARTH)
    b = np.searchsorted(ids, e.b_id)
    try:
        graph = make_graph(planar, ids, R, t, e.kind, a, b, e.meas_R, e.meas_t, e.info)
    except InputError as err:
        line = _first_without_information(e, planar)
        raise G2OFormatError(name, line, str(err) if line == 0 else
                             "information matrix has no positive eigenvalue") from None
    if vertex is None:
        graph.R, graph.t = odometry_chain(graph)
    return graph


def _check_params(problems: _Problems, params: _Group | None) -> None:
    if params is None:
        return
    _check_duplicates(problems, params, params.ints[:, 0], what="parameter id")
    q = params.vals[:, 3:]
    off = (np.any(params.vals[:, :3] != 0.0, axis=1)
           | (np.linalg.norm(q[:, :3], axis=1) > _MIN_QUAT_NORM * np.linalg.norm(q, axis=1))
           | (np.linalg.norm(q, axis=1) < _MIN_QUAT_NORM))
    problems.add_first(
        off, params.lines, "PARAMS_SE3OFFSET: only the identity sensor offset "
        "(0 0 0 0 0 0 1) is supported"
    )


def _check_duplicates(
    problems: _Problems, group: _Group, ids: np.ndarray, what: str = "vertex id"
) -> None:
    _, first = np.unique(ids, return_index=True)
    dup = np.ones(len(ids), dtype=bool)
    dup[first] = False
    problems.add_first(
        dup, group.lines, lambda k: f"duplicate {what} {ids[k]} "
        f"(first on line {group.lines[np.argmax(ids == ids[k])]})"
    )


def _vertex_poses(problems: _Problems, vertex: _Group) -> tuple[Array, Array]:
    v = vertex.vals
    t = np.zeros((len(v), 3))
    if vertex.tag == "VERTEX_SE2":
        t[:, :2] = v[:, :2]
        return geo.yaw_to_matrix(v[:, 2]), t
    t[:] = v[:, :3]
    return _quat(problems, vertex, v[:, 3:7]), t


def _edges_of(problems: _Problems, g: _Group, params: _Group | None) -> _Edges:
    m = len(g.lines)
    v = g.vals
    meas_t = np.zeros((m, 3))
    meas_R = np.broadcast_to(np.eye(3), (m, 3, 3)).copy()
    earth = np.full(m, EARTH, dtype=np.int64)
    if g.tag == "EDGE_SE2":
        kind = EdgeKind.RELATIVE
        meas_t[:, :2] = v[:, :2]
        meas_R = geo.yaw_to_matrix(v[:, 2])
        info = _embed(_sym_from_upper(v[:, 3:], 3), _PLANAR_ROWS)
    elif g.tag == "EDGE_SE3:QUAT":
        kind = EdgeKind.RELATIVE
        meas_t[:] = v[:, :3]
        meas_R = _quat(problems, g, v[:, 3:7])
        info = _sym_from_upper(v[:, 7:], 6)
    elif g.tag == "EDGE_PRIOR_SE2_XY":
        kind = EdgeKind.POSITION
        meas_t[:, :2] = v[:, :2]
        info = _embed(_sym_from_upper(v[:, 2:], 2), _XY_ROWS)
    elif g.tag == "EDGE_SE3_XYZ_PRIOR":
        kind = EdgeKind.POSITION
        meas_t[:] = v[:, :3]
        info = _embed(_sym_from_upper(v[:, 3:], 3), _XYZ_ROWS)
    elif g.tag == "EDGE_PRIOR_SE2":
        kind = EdgeKind.ORIENTATION
        meas_t[:, :2] = v[:, :2]
        meas_R = geo.yaw_to_matrix(v[:, 2])
        info = _embed(_sym_from_upper(v[:, 3:], 3), _PLANAR_ROWS)
    else:  # EDGE_SE3_PRIOR
        kind = EdgeKind.ORIENTATION
        meas_t[:] = v[:, :3]
        meas_R = _quat(problems, g, v[:, 3:7])
        info = _sym_from_upper(v[:, 7:], 6)
    if kind == EdgeKind.ORIENTATION:
        problems.add_first(
            np.any(info[:, :3, :] != 0.0, axis=(1, 2)), g.lines,
            f"{g.tag}: only orientation priors are supported (information on x, y, z must "
            "be zero; use the position prior tag for GPS)",
        )
    if kind == EdgeKind.RELATIVE:
        a_id, b_id = g.ints[:, 0], g.ints[:, 1]
        problems.add_first(a_id == b_id, g.lines, f"{g.tag}: edge from a node to itself")
    else:
        a_id, b_id = earth, g.ints[:, 0]
        if g.ints.shape[1] == 2:
            _check_param_refs(problems, g, params)
    kinds = np.full(m, kind, dtype=np.int8)
    return _Edges(g.lines, kinds, a_id, b_id, meas_R, meas_t, info)


def _check_param_refs(problems: _Problems, g: _Group, params: _Group | None) -> None:
    pid = g.ints[:, 1]
    known = np.zeros(len(pid), dtype=bool) if params is None else np.isin(pid, params.ints[:, 0])
    problems.add_first(
        ~known, g.lines,
        lambda k: f"{g.tag}: parameter {pid[k]} is not defined by a PARAMS_SE3OFFSET line",
    )


def _check_semi_definite(problems: _Problems, e: _Edges, planar: bool) -> None:
    """Refuse information that is indefinite in the coordinates its edge constrains.

    The solvers would clamp it to a floor, silently trusting a direction the file calls
    impossible; the nodes refuse such covariances. Semi-definite (singular) matrices pass:
    they are conditioned as the graph is built. Negative-definite ones are left to the
    "no positive eigenvalue" check.
    """
    dof = _PLANAR_ROWS if planar else _ALL_ROWS
    low = np.zeros(len(e.kind))
    high = np.zeros(len(e.kind))
    negative = np.zeros(len(e.kind), dtype=bool)
    for k, rows in KIND_ROWS.items():
        sel = np.flatnonzero(e.kind == k)
        rows = np.intersect1d(rows, dof)
        if len(sel):
            block = e.info[np.ix_(sel, rows, rows)]
            # Scaled by the largest entry, any finite magnitude is tested scale-free.
            scale = np.max(np.abs(block), axis=(1, 2))
            scale[scale == 0.0] = 1.0
            eig = np.linalg.eigvalsh(block / scale[:, None, None])
            low[sel], high[sel] = eig[:, 0] * scale, eig[:, -1] * scale
            # A negative diagonal entry is never rounding of a semi-definite matrix.
            negative[sel] = (eig[:, 0] < -_INFO_PSD_RTOL) | np.any(
                np.diagonal(block, axis1=1, axis2=2) < 0.0, axis=1)
    problems.add_first(
        negative & (high > 0.0), e.lines, lambda k: "information matrix is indefinite "
        f"(smallest eigenvalue {low[k]:.3g}, largest {high[k]:.3g})"
    )


def _first_without_information(e: _Edges, planar: bool) -> int:
    """Line of the first edge whose information has no positive eigenvalue (0: none)."""
    dof = _PLANAR_ROWS if planar else _ALL_ROWS
    bad = np.zeros(len(e.kind), dtype=bool)
    for k, rows in KIND_ROWS.items():
        sel = np.flatnonzero(e.kind == k)
        rows = np.intersect1d(rows, dof)
        if len(sel):
            top = np.linalg.eigvalsh(e.info[np.ix_(sel, rows, rows)])[:, -1]
            bad[sel] = top <= 0.0
    return int(e.lines[np.argmax(bad)]) if np.any(bad) else 0


def write_g2o(
    path: PathLike, graph: PoseGraph, R: Array | None = None, t: Array | None = None
) -> None:
    """Write ``graph`` to a g2o file with the estimate ``(R, t)`` (default: the graph's own).

    Planar graphs are written with the SE2 tags (theta = yaw), others with the SE3:QUAT tags;
    a ``VERTEX`` line for every node, then every edge in the graph's order. Floats are
    written at round-trip precision, so :func:`read_g2o` gives back the same ids, estimate,
    measurements and information: bitwise for planar graphs whose rotations are exact
    :func:`~h2o_slam.core.geometry.yaw_to_matrix` images (anything read from a file), within
    about 1e-15 for rotations that pass through a quaternion.

    Args:
        path: file to write (created or replaced).
        graph: the graph.
        R: rotations, shape ``(N, 3, 3)``.
        t: positions in m, shape ``(N, 3)``.
    """
    Path(path).write_text(format_g2o(graph, R, t), encoding="utf-8")


def format_g2o(graph: PoseGraph, R: Array | None = None, t: Array | None = None) -> str:
    """The text :func:`write_g2o` writes (same arguments, without the file)."""
    R = graph.R if R is None else np.asarray(R, dtype=float)
    t = graph.t if t is None else np.asarray(t, dtype=float)
    n = graph.num_nodes
    if R.shape != (n, 3, 3) or t.shape != (n, 3):
        raise ValueError(f"estimate shapes {R.shape}, {t.shape} do not match {n} nodes")
    ids = graph.ids
    out: list[str] = []
    global_edges = graph.kind != EdgeKind.RELATIVE
    if not graph.planar and np.any(global_edges):
        out.append("PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1")
    if graph.planar:
        vals = np.column_stack([t[:, :2], _exact_yaw(R)])
        out += _format("VERTEX_SE2", [ids], vals)
    else:
        out += _format("VERTEX_SE3:QUAT", [ids], np.column_stack([t, geo.matrix_to_quat(R)]))
    edge_lines: list[str] = [""] * graph.num_edges
    for kind in EdgeKind:
        sel = np.flatnonzero(graph.kind == kind)
        if len(sel):
            for k, line in zip(sel, _edge_lines(graph, kind, sel), strict=True):
                edge_lines[k] = line
    out += edge_lines
    return "\n".join(out) + "\n"


def _edge_lines(graph: PoseGraph, kind: EdgeKind, sel: np.ndarray) -> list[str]:
    ids = graph.ids
    mt, mR, info = graph.meas_t[sel], graph.meas_R[sel], graph.info[sel]
    b = ids[graph.b[sel]]
    pid = np.zeros(len(sel), dtype=np.int64)
    if graph.planar:
        planar_info = _upper(info[:, _PLANAR_ROWS[:, None], _PLANAR_ROWS[None, :]])
        if kind == EdgeKind.RELATIVE:
            vals = np.column_stack([mt[:, :2], _exact_yaw(mR), planar_info])
            return _format("EDGE_SE2", [ids[graph.a[sel]], b], vals)
        if kind == EdgeKind.POSITION:
            vals = np.column_stack([mt[:, :2], _upper(info[:, :2, :2])])
            return _format("EDGE_PRIOR_SE2_XY", [b], vals)
        vals = np.column_stack([mt[:, :2], _exact_yaw(mR), planar_info])
        return _format("EDGE_PRIOR_SE2", [b], vals)
    if kind == EdgeKind.RELATIVE:
        vals = np.column_stack([mt, geo.matrix_to_quat(mR), _upper(info)])
        return _format("EDGE_SE3:QUAT", [ids[graph.a[sel]], b], vals)
    if kind == EdgeKind.POSITION:
        vals = np.column_stack([mt, _upper(info[:, :3, :3])])
        return _format("EDGE_SE3_XYZ_PRIOR", [b, pid], vals)
    vals = np.column_stack([mt, geo.matrix_to_quat(mR), _upper(info)])
    return _format("EDGE_SE3_PRIOR", [b, pid], vals)


def _upper(M: Array) -> Array:
    iu, ju = np.triu_indices(M.shape[-1])
    return M[:, iu, ju]


def _format(tag: str, int_cols: list[np.ndarray], vals: Array) -> list[str]:
    # repr() of a Python float is the shortest string that reads back to the same bits.
    ints = np.column_stack(int_cols).tolist()
    return [
        f"{tag} {' '.join(map(str, i))} {' '.join(map(repr, v))}"
        for i, v in zip(ints, vals.tolist(), strict=True)
    ]


def _exact_yaw(R: Array) -> Array:
    """Yaw angles (rad) whose :func:`~h2o_slam.core.geometry.yaw_to_matrix` is ``R`` bit for bit.

    ``atan2`` of a rotation's entries can land an ulp away from the angle the matrix was
    made from, or a turn away from it (files hold angles such as 3.141593 > π); the floats
    next to ``atan2`` and to ``atan2 ± 2π`` are tried so that reading the file back gives
    the same matrix. Matrices that are not exact images of an angle keep ``atan2``.
    """
    yaw = geo.matrix_to_yaw(R)
    c, s = R[:, 0, 0], R[:, 1, 0]
    todo = ~((np.cos(yaw) == c) & (np.sin(yaw) == s))
    for base in (yaw, yaw + 2.0 * np.pi, yaw - 2.0 * np.pi):
        lo = hi = base
        for step in range(_YAW_ULPS + 1):
            if not np.any(todo):
                return yaw
            if step:
                lo, hi = np.nextafter(lo, -np.inf), np.nextafter(hi, np.inf)
            for cand in (lo, hi):
                hit = todo & (np.cos(cand) == c) & (np.sin(cand) == s)
                yaw = np.where(hit, cand, yaw)
                todo &= ~hit
    return yaw
