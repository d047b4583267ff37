"""The node's map on disk: crash-safe saves (SIGKILL at random instants) and a corpus of
damaged maps, each refused with one line naming the file, never loaded wrong."""

from __future__ import annotations

import hashlib
import json
import os
import random
import re
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from h2o_slam.core.errors import InputError
from h2o_slam.io.map_store import MapFiles, MapStoreError, has_map, load_map
from h2o_slam.ros.mapper import Mapper, MapperConfig, restore

REPO = Path(__file__).resolve().parents[2]
NS = 10**8
CONFIG = MapperConfig(budget_ms=0.0, background="off")


def drive(mapper: Mapper, start: int, count: int) -> None:
    """Odometry along a gentle curve: every sample is a keyframe (0.6 m apart)."""
    for i in range(start, start + count):
        mapper.add_odometry(10**9 + i * NS, np.array([0.6 * i, 0.02 * i * i / 50, 0.03 * i]))


def small_map(nodes: int = 12) -> Mapper:
    mapper = Mapper(CONFIG)
    drive(mapper, 0, nodes)
    mapper.add_loop_closure(0, nodes - 1, np.array([0.6 * (nodes - 1), 0.0, 0.0]),
                            np.eye(3) * 0.5)
    mapper.add_gps(10**9 + 3 * NS, np.array([1.8, 0.1, 0.0]), np.eye(3))
    for _ in range(5):
        mapper.step(None)
    return mapper


# --- SIGKILL during saves ----------------------------------------------------------------

WORKER = textwrap.dedent("""
    import os, signal, sys, time
    import numpy as np
    sys.path.insert(0, sys.argv[3])
    from test_persistence import CONFIG, drive
    from h2o_slam.ros.mapper import Mapper

    path, log = sys.argv[1], sys.argv[2]
    base = int(sys.argv[4])
    mapper = Mapper(CONFIG)
    drive(mapper, 0, base)
    mapper.save(path)
    start = time.perf_counter()
    for _ in range(3):
        mapper.save(path)
    print(f"ready {(time.perf_counter() - start) / 3}", flush=True)
    signal.signal(signal.SIGCHLD, signal.SIG_IGN)  # children reaped as they die
    fd = os.open(log, os.O_WRONLY | os.O_APPEND | os.O_CREAT)
    for line in sys.stdin:  # one forked saver per trial: no import per trial
        pid = os.fork()
        if pid == 0:  # continues from the map on disk: generations only grow
            n = int(line.split()[1])
            drive(mapper, base, n - base)
            while True:
                drive(mapper, n, 1)
                n += 1
                os.write(fd, f"start {n}\\n".encode())
                mapper.save(path)
                os.write(fd, f"done {n}\\n".encode())
        print(f"pid {pid}", flush=True)
""")


def _last(log: Path) -> tuple[int, int | None]:
    """(last generation saved, generation being saved when killed or None)."""
    done, started = 0, None
    for line in log.read_text().splitlines():
        word, _, value = line.partition(" ")
        if word == "done" and value:
            done, started = int(value), None
        elif word == "start" and value:
            started = int(value)
    return done, started


@pytest.mark.slow
def test_sigkill_at_random_instants_always_leaves_a_loadable_map(tmp_path: Path) -> None:
    base, trials = 200, 50
    path, log = tmp_path / "graph.g2o", tmp_path / "log"
    log.write_text("")
    worker = subprocess.Popen(
        [sys.executable, "-c", WORKER, str(path), str(log), str(Path(__file__).parent),
         str(base)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=REPO)
    assert worker.stdin is not None and worker.stdout is not None
    rng = random.Random(13)
    loaded_new = loaded_old = 0
    try:
        first = worker.stdout.readline().split()
        assert first and first[0] == "ready", first
        save_s = float(first[1])
        previous = base
        for _ in range(trials):
            worker.stdin.write(f"go {previous}\n")
            worker.stdin.flush()
            pid = int(worker.stdout.readline().split()[1])
            time.sleep(rng.uniform(0.0, 3.0 * save_s))
            os.kill(pid, signal.SIGKILL)
            _wait_gone(pid)
            done, started = _last(log)
            if done == 0:  # killed before its first save ended: the previous map is the old
                done = previous
            mapper = restore(path, CONFIG)  # what load_map_on_start runs
            assert mapper is not None
            n = mapper.num_nodes
            assert n in (done, started), (n, done, started)
            loaded_new += n == started
            loaded_old += n != started
            assert mapper.keyframes.stamps[-1] == 10**9 + (n - 1) * NS
            mapper.close()
            previous = n
            log.write_text("")
    finally:
        worker.kill()
        worker.wait()
    # Kills landed inside saves: some restarts found the save in flight already switched,
    # others the map before it.
    print(f"{trials} kills: {loaded_old} restarts from the old map, {loaded_new} from the new")
    assert loaded_new > 0 and loaded_old > 0, (loaded_new, loaded_old)


def _wait_gone(pid: int, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.002)
    raise AssertionError(f"process {pid} did not die")


def test_every_state_of_the_switch_loads_old_or_new(tmp_path: Path) -> None:
    # The states a kill can leave, made by hand: each loads, and the next save tidies up.
    path = tmp_path / "graph.g2o"
    old = small_map(12)
    old.save(path)
    new = small_map(15)
    files = MapFiles.of(path)
    new.save(tmp_path / "next.g2o")
    staged = {files.g2o_new: tmp_path / "next.g2o", files.sidecar_new: tmp_path / "next.json"}
    # 1. the new g2o file written, not committed (also a torn one): the old map.
    files.g2o_new.write_bytes((tmp_path / "next.g2o").read_bytes()[:1000])
    files.sidecar_tmp.write_bytes((tmp_path / "next.json").read_bytes()[:300])
    assert restore(path, CONFIG).num_nodes == 12  # type: ignore[union-attr]
    # 2. committed, not switched: the new map.
    for dst, src in staged.items():
        dst.write_bytes(src.read_bytes())
    assert restore(path, CONFIG).num_nodes == 15  # type: ignore[union-attr]
    # 3. the g2o switched, the sidecar not yet: the new map.
    os.replace(files.g2o_new, files.g2o)
    assert restore(path, CONFIG).num_nodes == 15  # type: ignore[union-attr]
    # The next save completes the switch first, then writes its own map.
    small_map(17).save(path)
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("graph")) == [
        "graph.g2o", "graph.json"]
    assert restore(path, CONFIG).num_nodes == 17  # type: ignore[union-attr]


def test_a_first_save_killed_before_its_commit_is_no_map(tmp_path: Path) -> None:
    path = tmp_path / "graph.g2o"
    MapFiles.of(path).g2o_new.write_text("VERTEX_SE2 0 0 0")
    assert not has_map(path) and restore(path, CONFIG) is None


def test_round_trip_keeps_everything(tmp_path: Path) -> None:
    mapper = small_map()
    mapper.datum = (48.1, 11.5, 520.0)
    mapper.save(tmp_path / "graph.g2o")
    text = (tmp_path / "graph.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    json.loads(text, parse_constant=lambda token: pytest.fail(f"bare {token}"))
    restored = Mapper.load(tmp_path / "graph.g2o", CONFIG)
    np.testing.assert_allclose(restored.poses(), mapper.poses(), atol=1e-9)
    assert restored.keyframes.stamps == mapper.keyframes.stamps
    assert restored.datum == mapper.datum
    np.testing.assert_array_equal(restored.track.stamps(), mapper.track.stamps())


# --- saves that are refused ------------------------------------------------------------------


def test_an_empty_graph_is_not_saved_over_the_map(tmp_path: Path) -> None:
    path = tmp_path / "graph.g2o"
    small_map().save(path)
    before = path.read_bytes()
    with pytest.raises(MapStoreError, match="graph: nothing to save: the graph is empty"):
        Mapper(CONFIG).save(path)
    lonely = Mapper(CONFIG)
    drive(lonely, 0, 1)
    with pytest.raises(MapStoreError, match="no edges"):
        lonely.save(path)
    assert path.read_bytes() == before


def test_a_poisoned_graph_is_not_saved(tmp_path: Path) -> None:
    path = tmp_path / "graph.g2o"
    mapper = small_map()
    mapper.save(path)
    before = path.read_bytes(), path.with_suffix(".json").read_bytes()
    mapper.h2o.solver.tree.t[4, 0] = np.nan
    with pytest.raises(MapStoreError, match=r"graph.g2o: node poses \(t\): entry \d+ is not "
                       "finite"):
        mapper.save(path)
    assert (path.read_bytes(), path.with_suffix(".json").read_bytes()) == before
    mapper = small_map()
    mapper.keyframes.odom[3] = np.array([np.inf, 0.0, 0.0])
    with pytest.raises(MapStoreError, match="keyframe odometry: entry 3"):
        mapper.save(path)


def test_a_folder_that_cannot_be_written_keeps_the_old_map(tmp_path: Path) -> None:
    path = tmp_path / "graph.g2o"
    small_map().save(path)
    MapFiles.of(path).g2o_new.mkdir()  # the new file cannot be created
    with pytest.raises(MapStoreError, match="graph.g2o: save: "):
        small_map(20).save(path)
    assert restore(path, CONFIG).num_nodes == 12  # type: ignore[union-attr]


# --- a corpus of damaged maps ----------------------------------------------------------------

Damage = Callable[[Path, Path], None]


def _other_save(g2o: Path, side: Path) -> None:
    small_map(13).save(g2o.with_name("other.g2o"))
    g2o.write_bytes(g2o.with_name("other.g2o").read_bytes())


def _edit_json(change: Callable[[dict], None]) -> Damage:
    def damage(g2o: Path, side: Path) -> None:
        meta = json.loads(side.read_text())
        change(meta)
        side.write_text(json.dumps(meta))
    return damage


def _edit_g2o(change: Callable[[list[str]], list[str]], resign: bool = False) -> Damage:
    """Change the g2o lines; ``resign`` also updates the sidecar's digest, as an attacker
    (or a careless tool) that knows the format would."""
    def damage(g2o: Path, side: Path) -> None:
        text = "\n".join(change(g2o.read_text().splitlines())) + "\n"
        g2o.write_text(text)
        if resign:
            meta = json.loads(side.read_text())
            meta["g2o"]["sha256"] = hashlib.sha256(text.encode()).hexdigest()
            side.write_text(json.dumps(meta))
    return damage


def _swap_vertex_ids(lines: list[str]) -> list[str]:
    out = list(lines)
    a, b = out[2].split(), out[7].split()
    a[1], b[1] = b[1], a[1]
    out[2], out[7] = " ".join(a), " ".join(b)
    return out


def _swap_endpoints(tag_index: int) -> Callable[[list[str]], list[str]]:
    def change(lines: list[str]) -> list[str]:
        out = list(lines)
        edges = [k for k, line in enumerate(out) if line.startswith("EDGE_SE2 ")]
        k = edges[tag_index]
        f = out[k].split()
        f[1], f[2] = f[2], f[1]
        out[k] = " ".join(f)
        return out
    return change


def _replace_token(tag: str, field_no: int, token: str) -> Callable[[list[str]], list[str]]:
    def change(lines: list[str]) -> list[str]:
        out = list(lines)
        k = next(k for k, line in enumerate(out) if line.startswith(tag + " "))
        f = out[k].split()
        f[field_no] = token
        out[k] = " ".join(f)
        return out
    return change


def _set(path: str, value: object) -> Callable[[dict], None]:
    def change(meta: dict) -> None:
        node = meta
        keys: list[str | int] = [int(k) if k.isdigit() else k for k in path.split(".")]
        for key in keys[:-1]:
            node = node[key]  # type: ignore[index]
        node[keys[-1]] = value  # type: ignore[index]
    return change


def _reverse_stamps(meta: dict) -> None:
    meta["stamps_ns"][3], meta["stamps_ns"][4] = meta["stamps_ns"][4], meta["stamps_ns"][3]


CORPUS: dict[str, tuple[Damage, str, str]] = {
    # name: (damage, file named, what the reason says)
    "sidecar truncated": (lambda g, s: s.write_bytes(s.read_bytes()[:-200]), "json",
                          "sidecar: not JSON"),
    "sidecar empty": (lambda g, s: s.write_bytes(b""), "json", "sidecar: not JSON"),
    "sidecar missing": (lambda g, s: s.unlink(), "json", "sidecar: missing"),
    "sidecar not utf-8": (lambda g, s: s.write_bytes(b"\xff\xfe" + s.read_bytes()), "json",
                          "not UTF-8"),
    "sidecar bare NaN": (lambda g, s: s.write_text(s.read_text().replace(
        '"odom": [[0.0,', '"odom": [[NaN,', 1)), "json", "bare NaN is not JSON"),
    "sidecar Infinity": (lambda g, s: s.write_text(s.read_text().replace(
        '"odom": [[0.0,', '"odom": [[-Infinity,', 1)), "json", "bare -Infinity"),
    "sidecar 1e999": (lambda g, s: s.write_text(s.read_text().replace(
        '"odom": [[0.0,', '"odom": [[1e999,', 1)), "json", "odom: entry 0 is not finite"),
    "sidecar version 1": (_edit_json(_set("version", 1)), "json", "version: 1, expected 2"),
    "sidecar a list": (lambda g, s: s.write_text("[]"), "json", "not a JSON object"),
    "stamps reversed": (_edit_json(_reverse_stamps), "json",
                        r"stamps_ns\[4\]: \d+ is not after"),
    "stamp a string": (_edit_json(_set("stamps_ns.2", "12")), "json",
                       r"stamps_ns\[2\]: '12' is not a stamp"),
    "stamp negative": (_edit_json(_set("stamps_ns.0", -5)), "json", r"stamps_ns\[0\]"),
    "stamp a bool": (_edit_json(_set("stamps_ns.0", True)), "json", r"stamps_ns\[0\]"),
    "track stamps reversed": (_edit_json(lambda m: m["track_stamps_ns"].reverse()), "json",
                              r"track_stamps_ns\[1\]"),
    "odom a string": (_edit_json(_set("odom.2.0", "1.2")), "json", "odom: entry 6 is '1.2'"),
    "odom ragged": (_edit_json(_set("odom.2", [1.0, 2.0])), "json", "odom: expected N x 3"),
    "odom shifted": (_edit_json(_set("odom.5.0", 99.0)), "json",
                     r"odom\[5\]: differs from the odometry track"),
    "odom and track shifted": (_edit_json(lambda m: (_set("odom.5.0", 99.0)(m), _set(
        "track_poses.5.0", 99.0)(m))), "g2o", "EDGE_SE2 4 5: no odometry edge"),
    "odom huge": (_edit_json(lambda m: (_set("odom.5.0", 1e200)(m), _set(
        "track_poses.5.0", 1e200)(m))), "json", "odom: entry 15 is not finite"),
    "keyframe missing from track": (_edit_json(lambda m: m["track_stamps_ns"].__setitem__(
        6, m["track_stamps_ns"][6] + 1)), "json", r"stamps_ns\[6\]: keyframe stamp"),
    "fewer stamps than nodes": (_edit_json(lambda m: m["stamps_ns"].pop()), "json",
                                "stamps_ns: 11 entries for the 12 nodes"),
    "more nodes than the g2o": (_edit_json(lambda m: [m[k].append(m[k][-1]) for k in (
        "stamps_ns", "odom", "chain_cov")] and _set("g2o.nodes", 13)(m)), "json",
        r"stamps_ns\[12\]"),
    "chain_cov NaN start": (_edit_json(_set("chain_cov.0", [[0.1] * 3] * 3)), "json",
                            r"chain_cov\[0\]: must be null"),
    "chain_cov null": (_edit_json(_set("chain_cov.3", None)), "json", r"chain_cov\[3\]: null"),
    "chain_cov indefinite": (_edit_json(_set("chain_cov.3", [[1, 0, 0], [0, -1, 0],
                                                             [0, 0, 1]])), "json",
                             r"chain_cov\[3\]: not a symmetric positive definite"),
    "chain_cov scaled": (_edit_json(_set("chain_cov.3.0.0", 1.0)), "g2o",
                         "EDGE_SE2 2 3: no odometry edge"),
    "datum off the earth": (_edit_json(_set("datum", [123.0, 11.0, 0.0])), "json",
                            "datum: .* is not a latitude"),
    "datum short": (_edit_json(_set("datum", [1.0, 2.0])), "json", "datum: expected 3"),
    "g2o nodes mismatch": (_edit_json(_set("g2o.nodes", 0)), "json", "g2o.nodes: 0 is not"),
    "digest missing": (_edit_json(lambda m: m["g2o"].pop("sha256")), "json",
                       "g2o.sha256: missing"),
    "config missing": (_edit_json(lambda m: m.pop("config")), "json", "config: missing"),
    "chi2 NaN-ish string": (_edit_json(_set("g2o.chi2", "nan")), "json", "g2o.chi2: entry 0"),
    "g2o truncated": (lambda g, s: g.write_bytes(g.read_bytes()[:-150]), "g2o", "g2o"),
    "g2o cut mid-line": (lambda g, s: g.write_bytes(g.read_bytes()[:len(g.read_bytes()) // 2]),
                         "g2o", "g2o"),
    "g2o empty": (lambda g, s: g.write_bytes(b""), "g2o", "empty file"),
    "g2o missing": (lambda g, s: g.unlink(), "g2o", "cannot read"),
    "g2o NaN token": (_edit_g2o(_replace_token("VERTEX_SE2", 2, "nan")), "g2o",
                      "non-finite value"),
    "g2o inf information": (_edit_g2o(_replace_token("EDGE_SE2", 6, "inf")), "g2o",
                            "non-finite value"),
    "g2o garbage token": (_edit_g2o(_replace_token("EDGE_SE2", 3, "1.2.3")), "g2o",
                          "is not a number"),
    "g2o 3-D": (lambda g, s: g.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 "
                                          "0 0 0 0 0 1\nEDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1"
                                          " 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1\n"), "g2o",
                 "3-D tags"),
    "g2o vertex dropped": (_edit_g2o(lambda lines: lines[:1] + lines[2:]), "g2o",
                           "no VERTEX line"),
    "g2o extra vertex": (_edit_g2o(lambda lines: ["VERTEX_SE2 40 0 0 0"] + lines), "g2o",
                         "VERTEX_SE2: ids 0..40"),
    "g2o edge dropped": (_edit_g2o(lambda lines: lines[:-1]), "g2o",
                         "edges: 12 edges; graph.json says 13"),
    "vertex ids swapped": (_edit_g2o(_swap_vertex_ids), "g2o", "chi2: .* vertices or edges"),
    "vertex ids swapped, re-signed": (_edit_g2o(_swap_vertex_ids, resign=True), "g2o",
                                      "chi2: "),
    "odometry endpoints swapped": (_edit_g2o(_swap_endpoints(4)), "g2o",
                                   "EDGE_SE2 4 5: no odometry edge"),
    "loop closure endpoints swapped": (_edit_g2o(_swap_endpoints(-1), resign=True), "g2o",
                                       "chi2: "),
    "vertex moved 1 mm, re-signed": (_edit_g2o(_replace_token("VERTEX_SE2", 2, "0.001"),
                                               resign=True), "g2o", "chi2: "),
    "g2o from another save": (_other_save, "g2o", "VERTEX_SE2: ids 0..12"),
    "a byte flipped in a comment": (lambda g, s: g.write_bytes(g.read_bytes() + b"# x\n"), "g2o",
                                    "sha256: differs"),
    "indefinite GPS information": (_edit_g2o(_replace_token("EDGE_PRIOR_SE2_XY", 4, "-1"),
                                             resign=True), "g2o",
                                   # the g2o reader's check, naming the line
                                   r"graph\.g2o:\d+: information matrix is indefinite"),
}


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("map")
    small_map().save(folder / "graph.g2o")
    return folder / "graph.g2o", folder / "graph.json"


@pytest.mark.parametrize("name", sorted(CORPUS))
def test_damaged_map_is_refused_with_one_line_naming_the_file(
        name: str, saved: tuple[Path, Path], tmp_path: Path) -> None:
    damage, which, reason = CORPUS[name]
    g2o, side = tmp_path / "graph.g2o", tmp_path / "graph.json"
    g2o.write_bytes(saved[0].read_bytes())
    side.write_bytes(saved[1].read_bytes())
    damage(g2o, side)
    with pytest.raises(InputError) as info:
        restore(g2o, CONFIG)
    message = str(info.value)
    assert "\n" not in message
    named = g2o if which == "g2o" else side
    assert message.startswith(f"{named}:") or message.startswith(f"{g2o}:"), message
    if which == "json":
        assert message.startswith(f"{side}:"), message
    assert re.search(reason, message), message


def test_the_corpus_covers_the_reported_corruptions() -> None:
    for kind in ("stamps reversed", "vertex ids swapped", "odometry endpoints swapped",
                 "loop closure endpoints swapped", "g2o truncated", "sidecar truncated",
                 "g2o NaN token", "sidecar bare NaN"):
        assert kind in CORPUS
    assert len(CORPUS) >= 42


def test_node_refuses_a_damaged_map_at_start_with_one_line(
        saved: tuple[Path, Path], tmp_path: Path) -> None:
    g2o, side = tmp_path / "graph.g2o", tmp_path / "graph.json"
    g2o.write_bytes(saved[0].read_bytes())
    side.write_bytes(saved[1].read_bytes())
    _reverse_json_stamps(side)
    env = dict(os.environ)
    env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(REPO / "config" / "fastdds_localhost.xml")
    env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    proc = subprocess.run(
        [sys.executable, "-m", "h2o_slam.ros.h2o_node", "--ros-args", "-p", f"map_file:={g2o}",
         "-p", "load_map_on_start:=true", "-r", f"__ns:=/persist{os.getpid()}"],
        env=env, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"h2o_node: {side}: stamps_ns[4]:"), lines


def _reverse_json_stamps(side: Path) -> None:
    meta = json.loads(side.read_text())
    _reverse_stamps(meta)
    side.write_text(json.dumps(meta))


def test_load_map_reads_only(saved: tuple[Path, Path]) -> None:
    before = {p: p.stat().st_mtime_ns for p in saved}
    load_map(saved[0])
    assert {p: p.stat().st_mtime_ns for p in saved} == before


def test_save_service_refuses_an_empty_graph_and_keeps_the_map(tmp_path: Path) -> None:
    import rclpy
    from rclpy.context import Context
    from rclpy.parameter import Parameter
    from std_srvs.srv import Trigger

    from h2o_slam.ros.h2o_node import H2ONode

    path = tmp_path / "graph.g2o"
    small_map().save(path)
    before = path.read_bytes()
    context = Context()
    rclpy.init(context=context)
    try:
        node = H2ONode(context=context, namespace=f"/persist_srv{os.getpid()}",
                       parameter_overrides=[Parameter("map_file", value=str(path)),
                                            Parameter("budget_ms", value=0.0)])
        try:
            answer = node._srv_save(Trigger.Request(), Trigger.Response())
            assert not answer.success and "the graph is empty" in answer.message
            assert path.read_bytes() == before
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
