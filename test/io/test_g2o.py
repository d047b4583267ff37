"""g2o reading and writing: round trips, odometry start, every error path, real files."""

from __future__ import annotations

import os
import re
import time
from pathlib import Path

import numpy as np
import pytest

from h2o_slam.core import geometry as geo
from h2o_slam.core.errors import G2OFormatError, InputError
from h2o_slam.core.graph import EARTH, EdgeKind, PoseGraph, chi2, make_graph, odometry_chain
from h2o_slam.io.g2o import read_g2o, write_g2o
from h2o_slam.io.synthetic import grid3d, manhattan

# The folder of the public pose graphs, when the environment gives one (H2O_POSEGRAPHS; see
# bench/README.md for where they come from); the tests that read them are skipped otherwise.
POSEGRAPHS_ENV = "H2O_POSEGRAPHS"

INFO3 = "1 0 0 1 0 1"
INFO6 = " ".join(str(v) for v in np.eye(6)[np.triu_indices(6)].astype(int))


def write(tmp_path: Path, text: str, name: str = "g.g2o") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def assert_same_graph(g: PoseGraph, h: PoseGraph, rot_atol: float = 0.0) -> None:
    for name in ("ids", "kind", "a", "b", "t", "meas_t", "info"):
        np.testing.assert_array_equal(getattr(h, name), getattr(g, name), err_msg=name)
    assert h.planar == g.planar
    if rot_atol == 0.0:
        np.testing.assert_array_equal(h.R, g.R)
        np.testing.assert_array_equal(h.meas_R, g.meas_R)
    else:
        np.testing.assert_allclose(h.R, g.R, rtol=0, atol=rot_atol)
        np.testing.assert_allclose(h.meas_R, g.meas_R, rtol=0, atol=rot_atol)


# --- round trips ---------------------------------------------------------------------------


@pytest.mark.parametrize("gps_every", [0, 7])
def test_planar_round_trip_is_bitwise(tmp_path: Path, gps_every: int) -> None:
    g = manhattan(300, seed=4, gps_every=gps_every).graph
    assert g.planar
    write_g2o(tmp_path / "out.g2o", g)
    h = read_g2o(tmp_path / "out.g2o")
    assert_same_graph(g, h)
    assert chi2(h) == chi2(g)
    assert np.any(h.kind == EdgeKind.POSITION) == (gps_every > 0)


def test_3d_round_trip(tmp_path: Path) -> None:
    g = grid3d(200, seed=2, gps_every=5).graph
    write_g2o(tmp_path / "out.g2o", g)
    h = read_g2o(tmp_path / "out.g2o")
    assert_same_graph(g, h, rot_atol=5e-15)
    assert chi2(h) == pytest.approx(chi2(g), rel=1e-10)
    text = (tmp_path / "out.g2o").read_text()
    assert text.startswith("PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1\n")
    assert "EDGE_SE3_XYZ_PRIOR 0 0 " in text


def test_round_trip_writes_given_estimate(tmp_path: Path) -> None:
    syn = manhattan(50, seed=1)
    write_g2o(tmp_path / "truth.g2o", syn.graph, syn.truth_R, syn.truth_t)
    h = read_g2o(tmp_path / "truth.g2o")
    np.testing.assert_array_equal(h.t, syn.truth_t)
    np.testing.assert_array_equal(h.R, syn.truth_R)
    with pytest.raises(ValueError, match="do not match"):
        write_g2o(tmp_path / "bad.g2o", syn.graph, syn.truth_R[:3], syn.truth_t)


def _sparse_id_graph(planar: bool) -> PoseGraph:
    rng = np.random.default_rng(11)
    ids = np.array([3, 7, 10, 42, 1000])
    n = len(ids)
    if planar:
        R = geo.yaw_to_matrix(rng.uniform(-np.pi, np.pi, n))
        t = np.column_stack([rng.normal(size=(n, 2)), np.zeros(n)])
        dof = [0, 1, 5]
    else:
        R = geo.so3_exp(rng.normal(size=(n, 3)))
        t = rng.normal(size=(n, 3))
        dof = list(range(6))
    pairs = [(0, 1), (2, 1), (2, 3), (3, 4), (4, 0)]
    kind = [EdgeKind.RELATIVE] * len(pairs) + [EdgeKind.POSITION, EdgeKind.ORIENTATION]
    a = [p[0] for p in pairs] + [EARTH, EARTH]
    b = [p[1] for p in pairs] + [2, 4]
    mR, mt = geo.between(R[a[:5]], t[a[:5]], R[b[:5]], t[b[:5]])
    if planar:
        # Exact yaw matrices, as a planar graph read from a file has (see the next test).
        mR = geo.yaw_to_matrix(geo.matrix_to_yaw(mR))
    ori_R = geo.yaw_to_matrix(0.3)[None] if planar else geo.so3_exp(rng.normal(size=(1, 3)))
    meas_R = np.concatenate([mR, np.eye(3)[None], ori_R])
    gps_t = t[2] + [0.1, -0.2, 0.0 if planar else 0.3]
    meas_t = np.concatenate([mt, gps_t[None], np.zeros((1, 3))])
    info = np.zeros((7, 6, 6))
    for k in range(5):
        G = rng.normal(size=(len(dof), len(dof)))
        info[k][np.ix_(dof, dof)] = G @ G.T + np.eye(len(dof))
    pos = [0, 1] if planar else [0, 1, 2]
    info[5][np.ix_(pos, pos)] = np.diag(np.arange(1.0, len(pos) + 1))
    rot = [5] if planar else [3, 4, 5]
    info[6][np.ix_(rot, rot)] = 4.0 * np.eye(len(rot))
    return make_graph(planar, ids, R, t, kind, a, b, meas_R, meas_t, info)


@pytest.mark.parametrize("planar", [True, False])
def test_round_trip_sparse_ids_and_global_edges(tmp_path: Path, planar: bool) -> None:
    g = _sparse_id_graph(planar)
    write_g2o(tmp_path / "out.g2o", g)
    text = (tmp_path / "out.g2o").read_text()
    gps_tag, ori_tag = (("EDGE_PRIOR_SE2_XY", "EDGE_PRIOR_SE2 ") if planar
                        else ("EDGE_SE3_XYZ_PRIOR", "EDGE_SE3_PRIOR"))
    assert gps_tag in text and ori_tag in text
    h = read_g2o(tmp_path / "out.g2o")
    assert_same_graph(g, h, rot_atol=0.0 if planar else 5e-15)
    np.testing.assert_array_equal(h.ids, [3, 7, 10, 42, 1000])
    # Edges come back in their original order, global edges included.
    np.testing.assert_array_equal(h.kind, g.kind)
    assert chi2(h) == pytest.approx(chi2(g), rel=1e-12)


def test_planar_rotations_that_are_not_exact_yaw_images(tmp_path: Path) -> None:
    # Products of yaw matrices are rotations about z but not the cos/sin of any float angle;
    # they come back within an ulp, and from then on bit for bit.
    R = geo.yaw_to_matrix(np.linspace(-3, 3, 7))
    R = R @ R[::-1]
    g = manhattan(7, seed=0).graph.with_estimate(R, np.zeros((7, 3)))
    write_g2o(tmp_path / "a.g2o", g)
    h = read_g2o(tmp_path / "a.g2o")
    np.testing.assert_allclose(h.R, g.R, rtol=0, atol=4.5e-16)
    write_g2o(tmp_path / "b.g2o", h)
    assert_same_graph(h, read_g2o(tmp_path / "b.g2o"))


def test_written_floats_are_shortest_repr(tmp_path: Path) -> None:
    g = manhattan(5, seed=0).graph
    write_g2o(tmp_path / "out.g2o", g)
    first = (tmp_path / "out.g2o").read_text().splitlines()[1].split()
    assert first[0] == "VERTEX_SE2" and first[1] == "1"
    assert float(first[2]) == g.t[1, 0] and first[2] == repr(float(g.t[1, 0]))


def test_angles_beyond_pi_in_files_round_trip(tmp_path: Path) -> None:
    # Files hold angles like 3.141593 > π (MIT.g2o); writing must reproduce the matrix.
    path = write(tmp_path, "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 3.141593\n"
                 f"EDGE_SE2 0 1 1 0 3.141593 {INFO3}\nEDGE_SE2 1 0 -1 0 -3.3 {INFO3}\n")
    g = read_g2o(path)
    write_g2o(tmp_path / "out.g2o", g)
    assert_same_graph(g, read_g2o(tmp_path / "out.g2o"))


# --- reading -------------------------------------------------------------------------------


def test_file_without_vertices_starts_from_odometry(tmp_path: Path) -> None:
    path = write(tmp_path, f"""# odometry only, listed partly backwards
EDGE_SE2 0 1 1 0 1.5707963267948966 {INFO3}

EDGE_SE2 2 1 -1 0 0 {INFO3}
EDGE_SE2 2 0 0 0 0 {INFO3}
FIX 0
""")
    g = read_g2o(path)
    assert (g.num_nodes, g.num_edges) == (3, 3)
    np.testing.assert_allclose(g.t, [[0, 0, 0], [1, 0, 0], [1, 1, 0]], atol=1e-15)
    np.testing.assert_allclose(geo.matrix_to_yaw(g.R), [0, np.pi / 2, np.pi / 2], atol=1e-15)
    R, t = odometry_chain(g)
    np.testing.assert_array_equal(g.R, R)
    np.testing.assert_array_equal(g.t, t)


def test_sparse_ids_without_vertices(tmp_path: Path) -> None:
    path = write(tmp_path, f"EDGE_SE2 5 9 1 0 0 {INFO3}\nEDGE_SE2 9 20 2 0 0 {INFO3}\n"
                 f"EDGE_PRIOR_SE2_XY 20 3 0 1 0 1\n")
    g = read_g2o(path)
    np.testing.assert_array_equal(g.ids, [5, 9, 20])
    np.testing.assert_allclose(g.t[:, 0], [0, 1, 3])
    np.testing.assert_array_equal(g.a, [0, 1, EARTH])
    np.testing.assert_array_equal(g.b, [1, 2, 2])


def test_vertices_order_and_unused_vertices(tmp_path: Path) -> None:
    path = write(tmp_path, f"""VERTEX_SE2 10 1 2 0.5
VERTEX_SE2 2 3 4 0
VERTEX_SE2 7 0 0 0   # no edge uses this one
EDGE_SE2 10 2 0 0 0 {INFO3}
""")
    g = read_g2o(path)
    np.testing.assert_array_equal(g.ids, [2, 7, 10])
    np.testing.assert_array_equal(g.t[:, :2], [[3, 4], [0, 0], [1, 2]])
    np.testing.assert_array_equal(g.a, [2])
    np.testing.assert_array_equal(g.b, [0])


def test_3d_information_order_and_quaternions(tmp_path: Path) -> None:
    G = np.random.default_rng(0).normal(size=(6, 6))
    S = np.round(G @ G.T + 6 * np.eye(6), 3)
    upper = S[np.triu_indices(6)]
    q = np.array([0.0, 0.0, 1.0, 1.0])  # not normalized: 90° about z
    path = write(tmp_path, "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 2 3 0 0 0 2\n"
                 "EDGE_SE3:QUAT 0 1 1 2 3 " + " ".join(map(str, q)) + " "
                 + " ".join(map(repr, upper.tolist())) + "\n")
    g = read_g2o(path)
    np.testing.assert_allclose(g.meas_R[0], geo.yaw_to_matrix(np.pi / 2), atol=1e-15)
    np.testing.assert_array_equal(g.R[1], np.eye(3))
    np.testing.assert_array_equal(g.info[0], S)


def test_se2_information_order(tmp_path: Path) -> None:
    path = write(tmp_path, "EDGE_SE2 0 1 1 0 0 10 1 2 20 3 30\nEDGE_PRIOR_SE2_XY 1 0 0 5 1 6\n")
    g = read_g2o(path)
    S = g.info[0][np.ix_([0, 1, 5], [0, 1, 5])]
    np.testing.assert_array_equal(S, [[10, 1, 2], [1, 20, 3], [2, 3, 30]])
    np.testing.assert_array_equal(g.info[1][:2, :2], [[5, 1], [1, 6]])
    assert g.kind[1] == EdgeKind.POSITION


def test_crlf_comments_and_blank_lines(tmp_path: Path) -> None:
    path = tmp_path / "crlf.g2o"
    path.write_bytes(b"# header\r\n\r\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1 # trailing\r\n  \r\n")
    g = read_g2o(path)
    assert g.num_edges == 1


# --- errors --------------------------------------------------------------------------------

V0 = "VERTEX_SE2 0 0 0 0"
V1 = "VERTEX_SE2 1 1 0 0"
E01 = f"EDGE_SE2 0 1 1 0 0 {INFO3}"
Q0 = "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1"
Q1 = "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1"
EQ = f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {INFO6}"
PARAMS = "PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1"

ERROR_CASES = [
    # (lines, offending line, reason pattern)
    ([V0, V1, "# fine", "EDGE_SE2_FOO 0 1", E01], 4, "unknown tag 'EDGE_SE2_FOO'"),
    ([V0, V1, "VERTEX2 2 0 0 0", E01], 3, "unknown tag 'VERTEX2'"),
    ([V0, "VERTEX_SE2 1 1 0", E01], 2, "VERTEX_SE2 takes 4 fields after the tag, found 3"),
    ([V0, V1, E01 + " 7"], 3, "EDGE_SE2 takes 11 fields after the tag, found 12"),
    ([V0, V1, "EDGE_SE2 0 1 1 zero 0 " + INFO3], 3, "'zero' is not a number"),
    ([V0, V1, "EDGE_SE2 0 1.5 1 0 0 " + INFO3], 3, "'1.5' is not an integer id"),
    ([V0, "VERTEX_SE2 -1 1 0 0", "EDGE_SE2 0 -1 1 0 0 " + INFO3], 2, "negative id"),
    ([V0, V1, "EDGE_SE2 0 1 1 nan 0 " + INFO3], 3, "non-finite value"),
    ([V0, "VERTEX_SE2 1 inf 0 0", E01], 2, "non-finite value"),
    ([Q0, "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 0", EQ], 2, "zero quaternion"),
    ([Q0, Q1, f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 0 {INFO6}"], 3, "zero quaternion"),
    ([V0, V1, "VERTEX_SE2 0 5 5 0", E01], 3, r"duplicate vertex id 0 \(first on line 1\)"),
    ([V0, V1, f"EDGE_SE2 1 1 1 0 0 {INFO3}", E01], 3, "edge from a node to itself"),
    ([V0, V1, E01, "EDGE_SE2 0 1 1 0 0 -1 0 0 -1 0 -1"], 4,
     "information matrix has no positive eigenvalue"),
    ([V0, V1, "EDGE_SE2 0 1 1 0 0 0 0 0 0 0 0", E01], 3,
     "information matrix has no positive eigenvalue"),
    ([V0, V1, E01, "EDGE_SE2 0 1 1 0 0 1e6 0 0 1e6 0 -1"], 4,
     r"information matrix is indefinite \(smallest eigenvalue -1, largest 1e\+06\)"),
    ([V0, V1, "EDGE_SE2 0 1 1 0 0 1 2 0 1 0 1", E01], 3, "information matrix is indefinite"),
    ([V0, V1, E01, "EDGE_PRIOR_SE2_XY 1 0 0 4 0 -0.5"], 4, "information matrix is indefinite"),
    ([Q0, Q1, f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {INFO6[:-1]}-1"], 3,
     "information matrix is indefinite"),
    ([V0, E01], 2, "edge uses node 1, which has no VERTEX line"),
    ([V1, E01], 2, "edge uses node 0, which has no VERTEX line"),
    ([V0, V1, E01, "EDGE_PRIOR_SE2_XY 4 0 0 1 0 1"], 4, "node 4, which has no VERTEX"),
    ([V0, V1, E01, Q0], 4, "3-D tag VERTEX_SE3:QUAT in a file that line 1 made planar"),
    ([Q0, Q1, EQ, E01], 4, "planar tag EDGE_SE2 in a file that line 1 made 3-D"),
    ([Q0, Q1, EQ, "EDGE_SE3_XYZ_PRIOR 1 0 0 0 0 1 0 0 1 0 1"], 4,
     "parameter 0 is not defined by a PARAMS_SE3OFFSET line"),
    (["PARAMS_SE3OFFSET 0 0 0 0.1 0 0 0 1", Q0, Q1, EQ], 1,
     "only the identity sensor offset"),
    ([PARAMS, PARAMS, Q0, Q1, EQ], 2, r"duplicate parameter id 0 \(first on line 1\)"),
    ([V0, V1, E01, f"EDGE_PRIOR_SE2 1 0 0 0 {INFO3}"], 4, "only orientation priors"),
    ([V0, V1, E01, "FIX 0 one"], 4, "FIX: 'one' is not a non-negative integer id"),
    ([V0, V1, E01, "FIX"], 4, "FIX takes at least one node id"),
    ([V0, V1], 0, "no edges"),
    (["# nothing here", "", "   "], 0, "empty file"),
    ([], 0, "empty file"),
]


@pytest.mark.parametrize(("lines", "line", "reason"), ERROR_CASES)
def test_bad_lines_name_file_line_and_reason(
    tmp_path: Path, lines: list[str], line: int, reason: str
) -> None:
    path = write(tmp_path, "\n".join(lines) + "\n")
    with pytest.raises(G2OFormatError, match=rf"^{re.escape(str(path))}:{line}: .*{reason}"):
        read_g2o(path)


def test_error_carries_fields_and_is_an_input_error(tmp_path: Path) -> None:
    path = write(tmp_path, f"{V0}\n{V1}\nBOGUS 1\n{E01}\n")
    with pytest.raises(InputError) as info:
        read_g2o(path)
    err = info.value
    assert isinstance(err, G2OFormatError)
    assert (err.path, err.line, err.reason) == (str(path), 3, "unknown tag 'BOGUS'")


def test_earliest_bad_line_is_reported_across_tags(tmp_path: Path) -> None:
    # Numbers are converted per tag group; the error must still be the first in the file.
    path = write(tmp_path, "\n".join([
        V0, V1, E01, "EDGE_PRIOR_SE2_XY 1 0 x 1 0 1", "VERTEX_SE2 2 0 y 0",
        "EDGE_SE2 1 2 1 0 z " + INFO3]) + "\n")
    with pytest.raises(G2OFormatError, match=r":4: .*'x' is not a number"):
        read_g2o(path)


def test_earliest_semantic_error_is_reported(tmp_path: Path) -> None:
    # A zero quaternion in a vertex (line 2) comes before a self-loop edge (line 4).
    path = write(tmp_path, "\n".join([
        Q0, "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 0", EQ,
        f"EDGE_SE3:QUAT 1 1 1 0 0 0 0 0 1 {INFO6}"]) + "\n")
    with pytest.raises(G2OFormatError, match=r":2: .*zero quaternion"):
        read_g2o(path)


def test_not_utf8(tmp_path: Path) -> None:
    path = tmp_path / "bin.g2o"
    path.write_bytes(f"{V0}\n{V1}\n".encode() + b"EDGE_SE2 0 1 \xff\n")
    with pytest.raises(G2OFormatError, match=r":3: not UTF-8 text"):
        read_g2o(path)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        read_g2o(tmp_path / "absent.g2o")


# --- real benchmark files (opt-in: they live outside the project) --------------------------

EXPECTED_COUNTS = {
    "intel.g2o": (1728, 2512),
    "manhattan.g2o": (3500, 5453),
    "CSAIL.g2o": (1045, 1172),
    "MIT.g2o": (808, 827),
    "city10000.g2o": (10000, 20687),
    "kitti_00.g2o": (4541, 4677),
    "sphere2500.g2o": (2500, 4949),
    "parking-garage.g2o": (1661, 6275),
    "smallGrid3D.g2o": (125, 297),
    "tinyGrid3D.g2o": (9, 11),
}


def _posegraph_dir() -> Path | None:
    """The folder H2O_POSEGRAPHS names (None when it is not set); a name that is not a
    folder fails, as the graphs were asked for."""
    folder = os.environ.get(POSEGRAPHS_ENV, "")
    if not folder:
        return None
    assert Path(folder).is_dir(), f"{POSEGRAPHS_ENV}={folder} is not a folder"
    return Path(folder)


def _readme_table(folder: Path) -> dict[str, tuple[int, int, str]]:
    readme = folder.parent / "README.md"
    rows: dict[str, tuple[int, int, str]] = {}
    if readme.is_file():
        for m in re.finditer(r"^\|\s*(\S+\.g2o)\s*\|\s*(\d+)\s*\|\s*(\d+)\s*\|\s*(SE[23])\s*\|",
                             readme.read_text(), flags=re.M):
            rows[m[1]] = (int(m[2]), int(m[3]), m[4])
    return rows


@pytest.mark.parametrize("name", sorted(EXPECTED_COUNTS))
def test_real_posegraphs(name: str) -> None:
    folder = _posegraph_dir()
    if folder is None:
        pytest.skip("public pose graphs not given (set H2O_POSEGRAPHS to their folder)")
    table = _readme_table(folder)
    if table:
        assert table[name][:2] == EXPECTED_COUNTS[name], "README table changed"
    start = time.perf_counter()
    g = read_g2o(folder / name)
    elapsed = time.perf_counter() - start
    assert (g.num_nodes, g.num_edges) == EXPECTED_COUNTS[name]
    if table:
        assert g.planar == (table[name][2] == "SE2")
    assert np.isfinite(chi2(g))
    # city10000 (1.7 MB, 30k lines) reads in ~0.2 s here; the bound leaves room for slow CI.
    assert elapsed < 2.0


def test_semi_definite_information_is_read_and_conditioned(tmp_path: Path) -> None:
    """Singular but positive semi-definite information (no yaw information; x and y
    perfectly correlated, written to six digits) is read and eigen-clamped, not refused."""
    path = write(tmp_path, "\n".join([V0, V1, "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 0",
                                      "EDGE_SE2 0 1 1 0 0 0.333333 0.333333 0 0.333333 0 1",
                                      E01]) + "\n")
    graph = read_g2o(path)
    np.testing.assert_array_equal(graph.clamped_edges, [0, 1])
