"""Crash-safe storage of ``h2o_node``'s map: a g2o file and its JSON sidecar, switched together.

A map is two files: ``NAME.g2o`` (the graph and its estimate) and ``NAME.json`` (keyframe
stamps and odometry poses, the odometry track, the GPS datum). The sidecar is also the map's
manifest: it records the SHA-256, node and edge counts and χ² of the g2o file it belongs to,
so a g2o file from another save, or changed after saving, is refused.

**Saving** never writes over the map in place. The new pair is written beside the old one
(``NAME.g2o.new``, then the sidecar as ``NAME.json.new.tmp``), each file fsynced; renaming
the sidecar to ``NAME.json.new`` is the commit (one atomic rename, the folder fsynced). Then
``NAME.g2o.new`` replaces ``NAME.g2o`` and ``NAME.json.new`` replaces ``NAME.json``. A kill at
any instant therefore leaves either the old pair (no committed ``NAME.json.new``) or the new
one (``NAME.json.new`` and whichever of ``NAME.g2o.new`` / ``NAME.g2o`` its digest names);
:func:`load_map` finds it without writing anything, and the next save finishes the switch.
An empty map, one without edges, or one with a non-finite value is refused.

**Loading** validates everything it reads and refuses with one line naming the file, the
field and the reason (:class:`MapStoreError`): standard JSON (no bare ``NaN``), every field's
type, shape and finiteness, strictly increasing stamps, keyframes that are samples of the
odometry track, node ids ``0..N-1``, an odometry edge ``i-1 → i`` matching the sidecar's
odometry for every keyframe, positive definite information, χ² equal to the saved one, and
the digest.

No rclpy here: :mod:`h2o_slam.ros.mapper` delegates to this module, and the node to the mapper.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.errors import InputError
from h2o_slam.core.graph import EdgeKind, PoseGraph, edge_chi2
from h2o_slam.io.g2o import format_g2o, parse_g2o

Array = np.ndarray
PathLike = str | os.PathLike[str]

#: Sidecar format written and the only one read (1 wrote bare ``NaN``, which is not JSON).
SIDECAR_VERSION = 2
SIDECAR_FORMAT = "h2o_slam map sidecar"

#: Largest coordinate (m) a map may hold: far beyond any robot's ENU frame, far below
#: where squaring it overflows.
MAX_COORDINATE_M = 1e9

#: χ² recomputed from the g2o file must equal the saved one to this relative tolerance
#: (the file holds floats at round-trip precision; rotations pass through an angle).
CHI2_RTOL = 1e-6

_PLANAR = np.ix_(geo.PLANAR_DOF, geo.PLANAR_DOF)


class MapStoreError(InputError):
    """A map that cannot be saved or loaded: ``FILE: FIELD: reason`` on one line."""

    def __init__(self, path: PathLike, field_name: str, reason: str) -> None:
        self.path = os.fspath(path)
        self.field = field_name
        self.reason = reason
        super().__init__(f"{self.path}: {field_name}: {reason}")


@dataclass
class SavedMap:
    """What a map holds.

    Attributes:
        graph: the planar graph with its estimate; node ``i`` is keyframe ``i``.
        stamps_ns: keyframe stamps (int ns), shape ``(N,)``, strictly increasing.
        odom: keyframe odometry poses ``(x, y, yaw)`` in ``odom``, shape ``(N, 3)``.
        chain_cov: covariance of the odometry increment into each keyframe, ``(N, 3, 3)``;
            NaN for node 0, which starts the chain.
        track_stamps_ns, track_poses: every odometry sample, ``(K,)`` int ns and ``(K, 3)``
            (yaw unwrapped); the keyframes are among them.
        datum: GPS datum ``(lat_deg, lon_deg, alt_m)`` or ``None``.
        config: the mapper settings at the save (informative; not applied on load).
        weights: each edge's robust weight, ``(M,)`` in [0, 1] (0: a loop closure or fix
            held or dropped as an outlier); ``None``: all 1 (maps saved before robust
            estimation).
    """

    graph: PoseGraph
    stamps_ns: np.ndarray
    odom: Array
    chain_cov: Array
    track_stamps_ns: np.ndarray
    track_poses: Array
    datum: tuple[float, float, float] | None = None
    config: dict[str, Any] = field(default_factory=dict)
    weights: Array | None = None


@dataclass(frozen=True)
class MapFiles:
    """The files of the map saved at ``g2o`` (see the module docstring)."""

    g2o: Path
    sidecar: Path
    g2o_new: Path
    sidecar_new: Path
    sidecar_tmp: Path

    @classmethod
    def of(cls, path: PathLike) -> MapFiles:
        """The files of the map named by its g2o path."""
        g2o = Path(path)
        if g2o.suffix == ".json":
            raise MapStoreError(g2o, "map_file", "names the sidecar; give the .g2o file")
        sidecar = g2o.with_suffix(".json")
        return cls(g2o, sidecar, g2o.with_name(g2o.name + ".new"),
                   sidecar.with_name(sidecar.name + ".new"),
                   sidecar.with_name(sidecar.name + ".new.tmp"))


def has_map(path: PathLike) -> bool:
    """Something was saved at ``path`` (a complete map or not: :func:`load_map` decides)."""
    files = MapFiles.of(path)
    return files.g2o.exists() or files.sidecar.exists() or files.sidecar_new.exists()


# --- saving ------------------------------------------------------------------------------


def save_map(path: PathLike, saved: SavedMap) -> Path:
    """Write ``saved`` as the map at ``path`` (a ``.g2o`` name), crash-safely; returns the
    sidecar's path.

    Raises:
        MapStoreError: the map is empty, has no edges or holds a non-finite value (nothing
            is written), or the files cannot be written (the previous map is kept).
    """
    files = MapFiles.of(path)
    _check_saveable(files.g2o, saved)
    text = format_g2o(saved.graph).encode("utf-8")
    graph = saved.graph
    meta = {
        "format": SIDECAR_FORMAT,
        "version": SIDECAR_VERSION,
        "g2o": {"sha256": hashlib.sha256(text).hexdigest(), "bytes": len(text),
                "nodes": graph.num_nodes, "edges": graph.num_edges,
                "chi2": float(np.sum(edge_chi2(graph)))},
        "stamps_ns": [int(s) for s in saved.stamps_ns],
        "odom": np.asarray(saved.odom, dtype=float).tolist(),
        "chain_cov": [None if np.isnan(c).any() else c.tolist() for c in saved.chain_cov],
        "track_stamps_ns": [int(s) for s in saved.track_stamps_ns],
        "track_poses": np.asarray(saved.track_poses, dtype=float).reshape(-1, 3).tolist(),
        "datum": None if saved.datum is None else [float(v) for v in saved.datum],
        "edge_weights": None if saved.weights is None else
        np.asarray(saved.weights, dtype=float).tolist(),
        # Informative only; JSON has no inf (an unbounded loop gate), so such values are
        # written as strings.
        "config": {k: repr(v) if isinstance(v, float) and not math.isfinite(v) else v
                   for k, v in saved.config.items()},
    }
    side = json.dumps(meta, allow_nan=False).encode("utf-8")
    try:
        finish_switch(files)
        _write_synced(files.g2o_new, text)
        _write_synced(files.sidecar_tmp, side)
        os.replace(files.sidecar_tmp, files.sidecar_new)  # the commit
        _sync_folder(files.g2o.parent)
        finish_switch(files)
    except OSError as exc:
        for leftover in (files.sidecar_tmp,):
            leftover.unlink(missing_ok=True)
        raise MapStoreError(files.g2o, "save", exc.strerror or str(exc)) from None
    return files.sidecar


def finish_switch(files: MapFiles) -> None:
    """Complete a save that was committed but not switched (a kill after the commit): the
    new files take the map's names. A commit whose g2o file is gone is dropped."""
    if not files.sidecar_new.exists():
        files.g2o_new.unlink(missing_ok=True)  # an uncommitted save's leftover
        files.sidecar_tmp.unlink(missing_ok=True)
        return
    try:
        digest = _sidecar_digest(files.sidecar_new)
    except MapStoreError:
        digest = None
    if digest is not None and _digest_of(files.g2o_new) == digest:
        os.replace(files.g2o_new, files.g2o)
        _sync_folder(files.g2o.parent)
    if digest is not None and _digest_of(files.g2o) == digest:
        os.replace(files.sidecar_new, files.sidecar)
    else:
        files.sidecar_new.unlink()
    files.g2o_new.unlink(missing_ok=True)
    _sync_folder(files.g2o.parent)


def _check_saveable(path: Path, saved: SavedMap) -> None:
    graph = saved.graph
    if graph.num_nodes == 0:
        raise MapStoreError(path, "graph", "nothing to save: the graph is empty (after a "
                            "reset, or before the first keyframe); the saved map is kept")
    if graph.num_edges == 0:
        raise MapStoreError(path, "graph", "nothing to save: the graph has no edges yet; "
                            "the saved map is kept")
    checks: list[tuple[str, Array]] = [
        ("node poses (t)", graph.t), ("node poses (R)", graph.R),
        ("edge measurements (t)", graph.meas_t), ("edge measurements (R)", graph.meas_R),
        ("edge information", graph.info), ("keyframe odometry", np.asarray(saved.odom)),
        ("keyframe odometry covariances", np.asarray(saved.chain_cov)[1:]),
        ("odometry track", np.asarray(saved.track_poses)),
        ("datum", np.asarray(saved.datum if saved.datum is not None else [], dtype=float)),
    ]
    for what, values in checks:
        bad = ~np.isfinite(values.reshape(len(values), -1)).all(axis=1) if values.size else []
        if np.any(bad):
            k = int(np.argmax(bad))
            raise MapStoreError(path, what, f"entry {k} is not finite; a graph poisoned by "
                                "non-finite input is not saved (the saved map is kept)")
    chi2 = float(np.sum(edge_chi2(graph)))
    if not math.isfinite(chi2):
        raise MapStoreError(path, "chi2", f"is {chi2}; the saved map is kept")


def _write_synced(path: Path, data: bytes) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        os.fsync(fd)
    finally:
        os.close(fd)


def _sync_folder(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _digest_of(path: Path) -> str | None:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return None


def _sidecar_digest(path: Path) -> str:
    meta = _read_json(path)
    g2o = meta.get("g2o")
    digest = g2o.get("sha256") if isinstance(g2o, dict) else None
    if not isinstance(digest, str):
        raise MapStoreError(path, "g2o.sha256", "missing")
    return digest


# --- loading -----------------------------------------------------------------------------


def load_map(path: PathLike) -> SavedMap:
    """The map saved at ``path`` (a ``.g2o`` name): the new one when a save was committed
    but not switched when it was killed, else the current pair. Reads only.

    Raises:
        MapStoreError: a missing, unreadable, damaged or inconsistent file: one line
            naming the file, the field and the reason.
        G2OFormatError: a g2o line that cannot be read (file, line and reason).
    """
    files = MapFiles.of(path)
    if files.sidecar_new.exists():
        side_path = files.sidecar_new
        meta = _read_json(side_path)
        digest = _sidecar_digest(side_path)
        g2o_path = next((p for p in (files.g2o_new, files.g2o) if _digest_of(p) == digest),
                        None)
        if g2o_path is None:
            raise MapStoreError(side_path, "g2o.sha256", f"matches neither {files.g2o_new.name}"
                                f" nor {files.g2o.name}: the map's g2o file is lost")
    else:
        side_path, g2o_path = files.sidecar, files.g2o
        if not side_path.exists():
            raise MapStoreError(side_path, "sidecar", f"missing: {g2o_path.name} was not saved "
                                "by h2o_node (a map is the g2o file and this sidecar)")
        meta = _read_json(side_path)
    return _validated(g2o_path, side_path, meta)


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise MapStoreError(path, "sidecar", f"cannot read ({exc.strerror or exc})") from None

    def refuse(token: str) -> Any:
        raise ValueError(f"bare {token} is not JSON")

    try:
        meta = json.loads(data.decode("utf-8"), parse_constant=refuse)
    except UnicodeDecodeError as exc:
        raise MapStoreError(path, "sidecar", f"not UTF-8 text (byte {exc.start})") from None
    except json.JSONDecodeError as exc:
        raise MapStoreError(path, "sidecar", f"not JSON: {exc.msg} at line {exc.lineno} "
                            f"column {exc.colno} (truncated or damaged)") from None
    except ValueError as exc:
        raise MapStoreError(path, "sidecar", f"not standard JSON: {exc}") from None
    if not isinstance(meta, dict):
        raise MapStoreError(path, "sidecar", "not a JSON object")
    if meta.get("version") != SIDECAR_VERSION:
        raise MapStoreError(path, "version", f"{meta.get('version')!r}, expected "
                            f"{SIDECAR_VERSION} (version 1 maps must be saved again)")
    return meta


class _Sidecar:
    """Typed access to the sidecar's fields, each failure naming the field."""

    def __init__(self, path: Path, meta: dict[str, Any]) -> None:
        self.path = path
        self.meta = meta

    def fail(self, name: str, reason: str) -> MapStoreError:
        return MapStoreError(self.path, name, reason)

    def get(self, name: str) -> Any:
        node: Any = self.meta
        for part in name.split("."):
            if not isinstance(node, dict) or part not in node:
                raise self.fail(name, "missing")
            node = node[part]
        return node

    def integer(self, name: str, low: int = 0) -> int:
        value = self.get(name)
        if type(value) is not int or value < low:
            raise self.fail(name, f"{value!r} is not an integer >= {low}")
        return value

    def stamps(self, name: str) -> np.ndarray:
        values = self.get(name)
        if not isinstance(values, list):
            raise self.fail(name, "not a list")
        for k, v in enumerate(values):
            if type(v) is not int or not 0 <= v < 2**63:
                raise self.fail(f"{name}[{k}]", f"{v!r} is not a stamp (int ns >= 0)")
        stamps = np.asarray(values, dtype=np.int64)
        back = np.flatnonzero(np.diff(stamps) <= 0)
        if len(back):
            k = int(back[0]) + 1
            raise self.fail(f"{name}[{k}]", f"{stamps[k]} is not after {stamps[k - 1]} "
                            "(stamps must increase)")
        return stamps

    def numbers(self, name: str, shape: tuple[int, ...], values: Any = None) -> Array:
        """Nested lists of finite numbers of ``shape`` (``-1``: any length)."""
        values = self.get(name) if values is None else values
        arr = np.empty(0)
        try:
            arr = np.array(values, dtype=object)
        except ValueError:
            pass
        if arr.ndim != len(shape) or any(s not in (-1, a) for s, a in zip(shape, arr.shape,
                                                                           strict=True)):
            want = " x ".join("N" if s == -1 else str(s) for s in shape)
            raise self.fail(name, f"expected {want} numbers")
        flat = arr.reshape(-1)
        for k, v in enumerate(flat):
            if type(v) not in (int, float):
                raise self.fail(name, f"entry {k} is {v!r}, not a number")
        out = np.asarray(flat, dtype=float).reshape(arr.shape)
        bad = ~np.isfinite(out) | (np.abs(out) > MAX_COORDINATE_M * 1e6)
        if np.any(bad):
            raise self.fail(name, f"entry {int(np.argmax(bad.reshape(-1)))} is not finite "
                            f"(or beyond {MAX_COORDINATE_M * 1e6:g})")
        return out


def _validated(g2o_path: Path, side_path: Path, meta: dict[str, Any]) -> SavedMap:
    side = _Sidecar(side_path, meta)
    nodes = side.integer("g2o.nodes", 1)
    edges = side.integer("g2o.edges", 1)
    side.integer("g2o.bytes", 1)
    digest = side.get("g2o.sha256")
    saved_chi2 = side.numbers("g2o.chi2", ())
    stamps = side.stamps("stamps_ns")
    odom = side.numbers("odom", (-1, 3))
    chain = side.get("chain_cov")
    for name, length in (("stamps_ns", len(stamps)), ("odom", len(odom)),
                         ("chain_cov", len(chain) if isinstance(chain, list) else -1)):
        if length != nodes:
            raise side.fail(name, f"{length} entries for the {nodes} nodes of g2o.nodes")
    chain_cov = np.full((nodes, 3, 3), np.nan)
    if chain[0] is not None:
        raise side.fail("chain_cov[0]", "must be null: node 0 starts the odometry chain")
    for i in range(1, nodes):
        if chain[i] is None:
            raise side.fail(f"chain_cov[{i}]", "null, but only node 0 starts the chain")
        chain_cov[i] = side.numbers(f"chain_cov[{i}]", (3, 3), chain[i])
    _check_positive_definite(side, "chain_cov", chain_cov[1:], offset=1)
    track_stamps = side.stamps("track_stamps_ns")
    track = side.numbers("track_poses", (-1, 3))
    if len(track) != len(track_stamps):
        raise side.fail("track_poses", f"{len(track)} poses for {len(track_stamps)} stamps "
                        "in track_stamps_ns")
    _check_keyframes_on_track(side, stamps, odom, track_stamps, track)
    datum = _datum(side)
    weights = _weights(side, edges)
    config = side.get("config")
    if not isinstance(config, dict):
        raise side.fail("config", "not an object")
    for name, values in (("odom", odom[:, :2]), ("track_poses", track[:, :2])):
        if np.any(np.abs(values) > MAX_COORDINATE_M):
            raise side.fail(name, f"a coordinate beyond {MAX_COORDINATE_M:g} m")

    try:
        data = g2o_path.read_bytes()
    except OSError as exc:
        raise MapStoreError(g2o_path, "g2o", f"cannot read ({exc.strerror or exc})") from None
    graph = parse_g2o(os.fspath(g2o_path), data)
    _check_graph(g2o_path, side_path, graph, nodes, edges, odom, chain_cov)
    _check_clamped(g2o_path, graph, data)
    chi2 = float(np.sum(edge_chi2(graph)))
    if not math.isfinite(chi2):
        raise MapStoreError(g2o_path, "chi2", f"is {chi2} at the saved estimate")
    if abs(chi2 - float(saved_chi2)) > CHI2_RTOL * (abs(float(saved_chi2)) + 1.0):
        raise MapStoreError(g2o_path, "chi2", f"{chi2:.9g} at the file's estimate, but the map "
                            f"was saved at {float(saved_chi2):.9g} (g2o.chi2): vertices or "
                            "edges changed since the save")
    if hashlib.sha256(data).hexdigest() != digest:
        raise MapStoreError(g2o_path, "sha256", f"differs from g2o.sha256 in {side_path.name}: "
                            "the file changed after the save, or belongs to another save")
    return SavedMap(graph, stamps, odom, chain_cov, track_stamps, track, datum, config,
                    weights)


def _weights(side: _Sidecar, edges: int) -> Array | None:
    """``edge_weights``: absent or null (a map saved before robust estimation), or one
    weight in [0, 1] per edge."""
    if side.meta.get("edge_weights") is None:
        return None
    weights = side.numbers("edge_weights", (edges,))
    if np.any((weights < 0.0) | (weights > 1.0)):
        raise side.fail("edge_weights", f"entry {int(np.argmax((weights < 0) | (weights > 1)))} "
                        "is outside [0, 1]")
    return weights


def _check_positive_definite(side: _Sidecar, name: str, cov: Array, offset: int = 0) -> None:
    if not len(cov):
        return
    sym = np.abs(cov - np.swapaxes(cov, -1, -2)).max(axis=(1, 2)) <= 1e-9 * (
        np.abs(cov).max(axis=(1, 2)) + 1e-300)
    eig = np.linalg.eigvalsh(cov)
    bad = ~sym | ~(eig[:, 0] > 0.0)
    if np.any(bad):
        k = int(np.argmax(bad)) + offset
        raise side.fail(f"{name}[{k}]", "not a symmetric positive definite covariance")


def _check_keyframes_on_track(side: _Sidecar, stamps: np.ndarray, odom: Array,
                              track_stamps: np.ndarray, track: Array) -> None:
    pos = np.searchsorted(track_stamps, stamps)
    pos = np.minimum(pos, max(len(track_stamps) - 1, 0))
    found = (track_stamps[pos] == stamps) if len(track_stamps) else np.zeros(len(stamps), bool)
    if not np.all(found):
        k = int(np.argmin(found))
        raise side.fail(f"stamps_ns[{k}]", f"keyframe stamp {stamps[k]} is not a sample of "
                        "track_stamps_ns")
    on_track = track[pos]
    scale = 1.0 + np.abs(odom[:, :2]).max(axis=1)
    off = (np.abs(on_track[:, :2] - odom[:, :2]).max(axis=1) > 1e-9 * scale) | (
        np.abs(geo.wrap_angle(on_track[:, 2] - odom[:, 2])) > 1e-9)
    if np.any(off):
        k = int(np.argmax(off))
        raise side.fail(f"odom[{k}]", f"differs from the odometry track at stamp {stamps[k]}")


def _datum(side: _Sidecar) -> tuple[float, float, float] | None:
    if side.get("datum") is None:
        return None
    lat, lon, alt = (float(v) for v in side.numbers("datum", (3,)))
    if not (abs(lat) <= 90.0 and abs(lon) <= 180.0 and abs(alt) <= 1e5):
        raise side.fail("datum", f"({lat}, {lon}, {alt}) is not a latitude, longitude and "
                        "altitude")
    return lat, lon, alt


def _check_graph(path: Path, side_path: Path, graph: PoseGraph, nodes: int, edges: int,
                 odom: Array, chain_cov: Array) -> None:
    def fail(name: str, reason: str) -> MapStoreError:
        return MapStoreError(path, name, reason)

    if not graph.planar:
        raise fail("tags", "3-D tags; a map h2o_node saves is planar (VERTEX_SE2, EDGE_SE2)")
    if graph.num_nodes != nodes or not np.array_equal(graph.ids, np.arange(nodes)):
        raise fail("VERTEX_SE2", f"ids {_span(graph.ids)}; {side_path.name} says the map has "
                   f"nodes 0..{nodes - 1} (g2o.nodes)")
    if graph.num_edges != edges:
        raise fail("edges", f"{graph.num_edges} edges; {side_path.name} says {edges} "
                   "(g2o.edges)")
    kinds = set(np.unique(graph.kind).tolist()) - {EdgeKind.RELATIVE, EdgeKind.POSITION}
    if kinds:
        raise fail("edges", "orientation priors; a map h2o_node saves has relative (EDGE_SE2) "
                   "and GPS (EDGE_PRIOR_SE2_XY) edges only")
    for name, values in (("VERTEX_SE2", graph.t), ("edge measurements", graph.meas_t)):
        if np.any(np.abs(values) > MAX_COORDINATE_M):
            raise fail(name, f"a coordinate beyond {MAX_COORDINATE_M:g} m")
    rel = graph.kind == EdgeKind.RELATIVE
    for mask, rows, tag in ((rel, geo.PLANAR_DOF, "EDGE_SE2"),
                            (~rel, np.array([0, 1]), "EDGE_PRIOR_SE2_XY")):
        sel = np.flatnonzero(mask)
        if len(sel):
            eig = np.linalg.eigvalsh(graph.info[np.ix_(sel, rows, rows)])[:, 0]
            if not np.all(eig > 0.0):
                k = sel[int(np.argmin(eig > 0.0))]
                raise fail(_edge_name(graph, int(k), tag),
                           "information matrix is not positive definite")
    # Every keyframe hangs off the previous one by the odometry increment the sidecar holds.
    a, b = graph.a, graph.b
    chain = np.flatnonzero(rel & (b == a + 1))
    expected = _relative(odom[a[chain]], odom[b[chain]])
    meas_yaw = np.arctan2(graph.meas_R[chain, 1, 0], graph.meas_R[chain, 0, 0])
    scale = 1e-9 * (1.0 + np.abs(expected[:, :2]).max(axis=1, initial=0.0))
    ok = (np.abs(graph.meas_t[chain, :2] - expected[:, :2]).max(axis=1, initial=0.0) <= scale) \
        & (np.abs(geo.wrap_angle(meas_yaw - expected[:, 2])) <= 1e-9)
    info = graph.info[chain][:, _PLANAR[0], _PLANAR[1]]
    want = np.linalg.inv(chain_cov[b[chain]])
    ok &= np.abs(info - want).max(axis=(1, 2), initial=0.0) <= 1e-6 * (
        np.abs(want).max(axis=(1, 2), initial=0.0))
    covered = np.zeros(nodes, dtype=bool)
    covered[0] = True
    covered[b[chain[ok]]] = True
    if not np.all(covered):
        i = int(np.argmin(covered))
        raise fail(f"EDGE_SE2 {i - 1} {i}", "no odometry edge from node "
                   f"{i - 1} to node {i} matches {side_path.name}'s odometry and covariance "
                   "(swapped endpoints or ids, or the files belong to different saves)")


def _check_clamped(path: Path, graph: PoseGraph, data: bytes) -> None:
    """The reader eigen-clamps information matrices (ill-conditioned ones are legitimate);
    an indefinite one in a saved map is damage. Only clamped edges are looked at again."""
    if not len(graph.clamped_edges):
        return
    lines = (line.partition("#")[0].split() for line in data.decode("utf-8").splitlines())
    edge_lines = [fields for fields in lines if fields and fields[0].startswith("EDGE")]
    for k in graph.clamped_edges.tolist():
        fields = edge_lines[k]
        tag = fields[0]
        upper = np.array(fields[-6:] if tag == "EDGE_SE2" else fields[-3:], dtype=float)
        n = 3 if tag == "EDGE_SE2" else 2
        raw = np.zeros((n, n))
        raw[np.triu_indices(n)] = upper
        raw = raw + np.triu(raw, 1).T
        lam = np.linalg.eigvalsh(raw)
        if lam[0] < -1e-12 * abs(lam[-1]):
            raise MapStoreError(path, _edge_name(graph, k, tag),
                                "information matrix is not positive definite")


def _edge_name(graph: PoseGraph, k: int, tag: str) -> str:
    a, b = int(graph.a[k]), int(graph.ids[graph.b[k]])
    return f"{tag} {a} {b}" if graph.kind[k] == EdgeKind.RELATIVE else f"{tag} {b}"


def _span(ids: np.ndarray) -> str:
    if not len(ids):
        return "none"
    return f"{int(ids.min())}..{int(ids.max())} ({len(ids)} vertices)"


def _relative(a: Array, b: Array) -> Array:
    # The mapper's planar ``relative`` (kept here so that this module stays below it).
    d = b[..., :2] - a[..., :2]
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1],
                     geo.wrap_angle(b[..., 2] - a[..., 2])], axis=-1)
