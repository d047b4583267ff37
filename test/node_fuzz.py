"""Hypothesis inputs for both nodes and the drivers that feed them, shared by
``test/test_fuzz_nodes.py`` (a bounded run in CI) and ``bench/fuzz.py`` (long campaigns).

An example is a list of operations in plain data (so that hypothesis prints and shrinks
it): messages for every subscription, calls of every timer and service. Values are mostly
those of a robot driving about, with a tenth drawn from the hostile: NaN, ±inf, 1e200,
±1.7e308, subnormals, the bounds themselves, malformed strings and sizes, lying image
headers. The driver builds rclpy messages from them and calls the node's registered
callbacks as the executor would (``node.subscriptions``, ``node.timers``,
``node.services``), checking after every operation that

* no exception left a callback (the executor would have ended the node), and
* nothing non-finite was published (every float of every message handed to the sink) or
  is held (the mapper's poses, odometry track and keyframes; the odometer's track).
"""

from __future__ import annotations

import math
import struct
import uuid
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from hypothesis import strategies as st
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import SetParameters
from rclpy.context import Context
from rclpy.parameter import Parameter
from rclpy.subscription import Subscription
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, NavSatFix
from std_srvs.srv import SetBool, Trigger

from h2o_slam.ros.h2o_node import H2ONode
from hybrid_vo.vo_node import HybridVoNode

START_S = 1_700_000_000
DATUM = (37.4275, -122.1697, 30.0)
#: The hostile values every float may take: NaN, infinities, overflowing magnitudes,
#: subnormals, the coordinate bound (1e8 m) and just beyond it.
SPECIAL = (0.0, -0.0, 5e-324, 1e-300, 1e-13, 1e8, -1e8, 1.0000001e8, 1e200, -1e200,
           1.7e308, -1.79e308, math.inf, -math.inf, math.nan)


def mostly(normal: st.SearchStrategy[Any], hostile: st.SearchStrategy[Any],
           one_in: int = 10) -> st.SearchStrategy[Any]:
    """``normal`` values, and ``hostile`` ones about once in ``one_in`` draws."""
    return st.integers(0, one_in - 1).flatmap(lambda k: hostile if k == 0 else normal)


WILD = st.one_of(st.sampled_from(SPECIAL), st.floats())


def num(lo: float, hi: float) -> st.SearchStrategy[float]:
    """A float of a driving robot in ``[lo, hi]``, or a hostile one."""
    return mostly(st.floats(lo, hi, allow_nan=False), WILD)


INT32 = st.integers(-(2**31), 2**31 - 1)
UINT32 = st.integers(0, 2**32 - 1)
TEXT = st.text(max_size=24)

# -- shared pieces ------------------------------------------------------------------------------

#: A stamp step in ms (mostly forward, sometimes standing still or going back), or an
#: absolute (sec, nanosec) anywhere in the message's range.
STAMP = mostly(st.integers(1, 120).map(lambda ms: ("dt", ms)),
               st.one_of(st.integers(-500, 0).map(lambda ms: ("dt", ms)),
                         st.tuples(st.just("abs"), INT32, UINT32)), one_in=8)

QUAT = mostly(num(-math.pi, math.pi).map(lambda yaw: ("yaw", yaw)),
              st.tuples(st.just("q"), WILD, WILD, WILD, WILD), one_in=8)

COV6 = st.one_of(
    st.just(("zero",)),
    st.tuples(st.just("diag"), num(1e-4, 1.0), num(1e-4, 1.0), num(1e-5, 0.1)),
    st.tuples(st.just("scaled"), WILD),
    st.just(("huge_block",)),  # 1.7e308 on x, y, z: what killed hybrid_vo_node
    st.tuples(st.just("full"), st.lists(WILD, min_size=36, max_size=36)),
)

COV3 = st.one_of(
    st.tuples(st.just("diag"), num(1e-3, 25.0)),
    st.tuples(st.just("scaled"), WILD),
    st.tuples(st.just("full"), st.lists(WILD, min_size=9, max_size=9)),
)

POSE = st.tuples(num(-100.0, 100.0), num(-100.0, 100.0), num(-1.0, 1.0), QUAT)

ODOM = st.tuples(st.just("odom"), STAMP, POSE, COV6)
#: A step of the driving robot from its last pose: forward m and turn rad.
STEP = st.tuples(st.just("step"), st.floats(0.0, 1.0), st.floats(-0.3, 0.3))

REF = st.one_of(
    st.tuples(st.just("node"), mostly(st.integers(0, 40), st.integers(-3, 10**30))),
    st.tuples(st.just("stamp"), st.integers(-3000, 200)),  # ms relative to the clock
    st.tuples(st.just("text"), TEXT),
)
LOOP = st.tuples(st.just("loop"), STAMP, REF, REF, POSE, COV6)
#: A loop closure between two keyframes (indices modulo their number) that agrees with the
#: odometry up to ``noise`` m: these pass the gate, so the graph gets cycles.
TRUE_LOOP = st.tuples(st.just("true_loop"), st.integers(0, 10**6), st.integers(0, 10**6),
                      st.floats(0.0, 0.3))

GPS = st.tuples(
    st.just("gps"), STAMP,
    mostly(st.sampled_from([-1, 0, 1, 2]), st.integers(-128, 127)),
    num(DATUM[0] - 1e-3, DATUM[0] + 1e-3), num(DATUM[1] - 1e-3, DATUM[1] + 1e-3),
    num(0.0, 60.0), mostly(st.sampled_from([0, 1, 2, 3]), st.integers(0, 255)), COV3,
)

TIMER = st.tuples(st.just("timer"), st.integers(0, 7))


@dataclass
class Outcome:
    """What a run saw: inputs fed, exceptions that escaped, non-finite values published
    or held, and the rejections counted as unexpected (bugs the boundary caught)."""

    inputs: int = 0
    escaped: list[str] = field(default_factory=list)
    non_finite: list[str] = field(default_factory=list)
    unexpected: Counter[str] = field(default_factory=Counter)
    published: int = 0

    def merge(self, other: Outcome) -> None:
        """Add another run's counts."""
        self.inputs += other.inputs
        self.escaped += other.escaped
        self.non_finite += other.non_finite
        self.unexpected.update(other.unexpected)
        self.published += other.published


def non_finite_fields(msg: Any, path: str = "") -> list[str]:
    """Paths of the NaN/inf floats anywhere in an rclpy message."""
    types = getattr(type(msg), "get_fields_and_field_types", None)
    if types is None:
        return []
    bad = []
    for name, kind in types().items():
        value = getattr(msg, name)
        where = f"{path}.{name}"
        if kind in ("double", "float"):
            if not math.isfinite(value):
                bad.append(where)
        elif kind.startswith(("double[", "float[", "sequence<double", "sequence<float")):
            if not np.all(np.isfinite(np.asarray(value, dtype=float))):
                bad.append(where)
        elif kind.startswith("sequence<") and "/" in kind:
            for i, item in enumerate(value):
                bad += non_finite_fields(item, f"{where}[{i}]")
        elif "/" in kind:
            bad += non_finite_fields(value, where)
    return bad


class Clock:
    """Message time: every operation's stamp relative to the newest one."""

    def __init__(self) -> None:
        self.ns = START_S * 10**9

    def stamp(self, msg_stamp: Any, spec: tuple[Any, ...]) -> None:
        """Set ``msg_stamp`` from a ``STAMP`` draw."""
        if spec[0] == "dt":
            self.ns = max(0, self.ns + spec[1] * 10**6)
            msg_stamp.sec, msg_stamp.nanosec = divmod(self.ns, 10**9)
        else:
            msg_stamp.sec, msg_stamp.nanosec = spec[1], spec[2]


def _quaternion(q: Any, spec: tuple[Any, ...]) -> None:
    if spec[0] == "yaw":
        yaw = spec[1]
        with np.errstate(invalid="ignore"):  # sin(inf) is NaN here, not math's ValueError
            half = np.float64(yaw) / 2.0
            q.x, q.y, q.z, q.w = 0.0, 0.0, float(np.sin(half)), float(np.cos(half))
    else:
        q.x, q.y, q.z, q.w = (float(v) for v in spec[1:])


def _cov6(spec: tuple[Any, ...]) -> list[float]:
    kind = spec[0]
    if kind == "zero":
        return [0.0] * 36
    if kind == "diag":
        out = [0.0] * 36
        for i, v in zip((0, 7, 35), spec[1:], strict=True):
            out[i] = v * v if math.isfinite(v) and abs(v) < 1e150 else v
        out[14] = out[21] = out[28] = 1.0  # z, roll, pitch: unobserved, yet definite
        return out
    if kind == "scaled":
        return [spec[1] if i % 7 == 0 else 0.0 for i in range(36)]
    if kind == "huge_block":
        return [1.7e308 if i in (0, 1, 2, 6, 7, 8, 12, 13, 14) else (1.0 if i % 7 == 0 else 0.0)
                for i in range(36)]
    return [float(v) for v in spec[1]]


def _cov3(spec: tuple[Any, ...]) -> list[float]:
    if spec[0] == "diag":
        v = spec[1]
        return [v if i % 4 == 0 else 0.0 for i in range(9)]
    if spec[0] == "scaled":
        return [spec[1] if i % 4 == 0 else 0.0 for i in range(9)]
    return [float(v) for v in spec[1]]


def odometry_msg(clock: Clock, stamp: Any, pose: Any, cov: Any, frame: str = "odom",
                 child: str = "base_link") -> Odometry:
    """A ``nav_msgs/Odometry`` of an ``ODOM`` (or ``LOOP``) draw."""
    msg = Odometry()
    clock.stamp(msg.header.stamp, stamp)
    msg.header.frame_id, msg.child_frame_id = frame, child
    x, y, z, quat = pose
    p = msg.pose.pose.position
    p.x, p.y, p.z = float(x), float(y), float(z)
    _quaternion(msg.pose.pose.orientation, quat)
    msg.pose.covariance = _cov6(cov)
    return msg


def _ref_text(clock: Clock, ref: tuple[Any, ...]) -> str:
    if ref[0] == "node":
        return f"node/{ref[1]}"
    if ref[0] == "stamp":
        ns = max(0, clock.ns + ref[1] * 10**6)
        return f"stamp/{ns // 10**9}.{ns % 10**9:09d}"
    return str(ref[1])


def navsat_msg(clock: Clock, op: tuple[Any, ...]) -> NavSatFix:
    """A ``sensor_msgs/NavSatFix`` of a ``GPS`` draw."""
    _, stamp, status, lat, lon, alt, cov_type, cov = op
    msg = NavSatFix()
    clock.stamp(msg.header.stamp, stamp)
    msg.header.frame_id = "gps"
    msg.status.status = status
    msg.latitude, msg.longitude, msg.altitude = float(lat), float(lon), float(alt)
    msg.position_covariance_type = cov_type
    msg.position_covariance = _cov3(cov)
    return msg


class NodeDriver:
    """One node under test, its callbacks as the executor calls them, and the checks."""

    def __init__(self, node: Any) -> None:
        self.node = node
        self.outcome = Outcome()
        self.clock = Clock()
        self.pose = (0.0, 0.0, 0.0)  # the driving robot's, in odom
        node.sink = self._sink
        prefix = node.get_namespace().rstrip("/") + "/"
        self.subs = {sub.topic_name.removeprefix(prefix): sub for sub in node.subscriptions}
        self.timers = list(node.timers)
        self.services = {srv.srv_name.rsplit("/", 1)[-1]: srv for srv in node.services}

    def _sink(self, topic: str, msg: Any) -> None:
        self.outcome.published += 1
        bad = non_finite_fields(msg)
        if bad:
            self.outcome.non_finite.append(f"published on {topic}: {bad[:3]}")

    def call(self, what: str, fn: Any, *args: Any) -> Any:
        """Call one callback as the executor would; an exception is recorded as escaped."""
        self.outcome.inputs += 1
        try:
            return fn(*args)
        except Exception as exc:  # what the executor would have died of
            self.outcome.escaped.append(f"{what}: {type(exc).__name__}: {exc}")
            return None

    def deliver(self, key: str, msg: Any) -> None:
        """A message on the subscription ``key`` (topic suffix); a callback that takes the
        message info gets one, as from a publisher that loses nothing."""
        sub = self.subs[key]
        if sub._callback_type is Subscription.CallbackType.WithMessageInfo:
            self.call(key, sub.callback, msg, {"publication_sequence_number": None})
        else:
            self.call(key, sub.callback, msg)

    def tick(self, index: int) -> None:
        """Fire one of the node's timers."""
        timer = self.timers[index % len(self.timers)]
        self.call("timer", timer.callback)

    def service(self, name: str, request: Any) -> Any:
        """Call a service as a client's request would be served."""
        srv = self.services[name]
        return self.call(name, srv.callback, request, srv.srv_type.Response())

    def set_parameter(self, name: str, value: float) -> None:
        """``~/set_parameters`` with one double (range checks are rclpy's)."""
        request = SetParameters.Request()
        request.parameters = [ParameterMsg(name=name, value=Parameter(
            name, Parameter.Type.DOUBLE, value).get_parameter_value())]
        assert request.parameters[0].value.type == ParameterType.PARAMETER_DOUBLE
        self.service("set_parameters", request)

    def control(self, op: tuple[Any, ...]) -> None:
        """A ``timer``, ``service``, ``pause`` or ``param`` operation."""
        kind = op[0]
        if kind == "timer":
            self.tick(op[1])
        elif kind == "service":
            self.service(op[1], Trigger.Request())
        elif kind == "pause":
            self.service("pause", SetBool.Request(data=op[1]))
        elif kind == "param":
            self.set_parameter(op[1], op[2])
        else:
            raise ValueError(f"unknown operation {op!r}")

    def note_unexpected(self, counters: Counter[str]) -> None:
        """Record the rejections the boundary counted as unexpected."""
        self.outcome.unexpected = Counter(
            {k: v for k, v in counters.items() if "unexpected" in k})


# -- h2o_node -------------------------------------------------------------------------------------

H2O_SERVICE = st.one_of(
    st.tuples(st.just("service"), st.sampled_from(["exact_solve", "reset", "save_map"])),
    st.tuples(st.just("pause"), st.booleans()),
    st.tuples(st.just("param"), st.sampled_from(
        ["budget_ms", "keyframe_distance", "keyframe_angle", "loop_gate_chi2",
         "idle_budget_ms"]), WILD),
)

#: One ``h2o_node`` operation: odometry (most), loop closures, fixes, timers, services.
H2O_OP = st.one_of(STEP, STEP, STEP, ODOM, LOOP, TRUE_LOOP, GPS, TIMER, H2O_SERVICE)
H2O_OPS = st.lists(H2O_OP, min_size=1, max_size=40)
#: Valid inputs every example starts with, so that its operations meet a graph (keyframes,
#: a GPS datum and fix) rather than an empty node.
WARM_UP_STEPS = 12


def step_msg(driver: NodeDriver, forward_m: float, turn_rad: float) -> Odometry:
    """Odometry of the driving robot after a step, 50 ms after the clock."""
    x, y, yaw = driver.pose
    yaw += turn_rad
    driver.pose = (x + forward_m * math.cos(yaw), y + forward_m * math.sin(yaw), yaw)
    cov = ("diag", 0.01, 0.01, 0.001)
    return odometry_msg(driver.clock, ("dt", 50), (*driver.pose[:2], 0.0, ("yaw", yaw)), cov)


def _true_loop(driver: NodeDriver, op: tuple[Any, ...]) -> Odometry | None:
    kf = driver.node.mapper.keyframes
    if len(kf.odom) < 2:
        return None
    a, b = op[1] % len(kf.odom), op[2] % len(kf.odom)
    pa, pb = kf.odom[a], kf.odom[b]
    c, s = math.cos(pa[2]), math.sin(pa[2])
    dx, dy = pb[0] - pa[0], pb[1] - pa[1]
    rel = (c * dx + s * dy + op[3], -s * dx + c * dy, ("yaw", pb[2] - pa[2]))
    return odometry_msg(driver.clock, ("dt", 1), (rel[0], rel[1], 0.0, rel[2]),
                        ("diag", 0.1, 0.1, 0.02), f"node/{a}", f"node/{b}")


def make_h2o_node(context: Context, map_dir: Path) -> H2ONode:
    """An ``h2o_node`` whose solver steps are deterministic (``budget_ms`` 0: inline)."""
    overrides = [Parameter("budget_ms", value=0.0), Parameter("datum", value=list(DATUM)),
                 Parameter("map_file", value=str(map_dir / f"{uuid.uuid4().hex[:8]}.g2o"))]
    return H2ONode(namespace="/fuzz" + uuid.uuid4().hex[:8], context=context,
                   parameter_overrides=overrides)


def run_h2o(driver: NodeDriver, ops: list[tuple[Any, ...]]) -> Outcome:
    """Feed ``ops`` to an ``h2o_node`` driver; returns what it saw."""
    node: H2ONode = driver.node
    clock = driver.clock
    warm_up = [("step", 0.6, 0.1)] * WARM_UP_STEPS
    warm_up.insert(WARM_UP_STEPS // 2, ("gps", ("dt", 0), 0, *DATUM, 2, ("diag", 1.0)))
    for op in warm_up + list(ops):
        kind = op[0]
        if kind == "step":
            driver.deliver("odom", step_msg(driver, op[1], op[2]))
        elif kind == "true_loop":
            msg = _true_loop(driver, op)
            if msg is not None:
                driver.deliver("loop_closure", msg)
        elif kind == "odom":
            driver.deliver("odom", odometry_msg(clock, op[1], op[2], op[3]))
        elif kind == "loop":
            _, stamp, a, b, pose, cov = op
            msg = odometry_msg(clock, stamp, pose, cov, _ref_text(clock, a), _ref_text(clock, b))
            driver.deliver("loop_closure", msg)
        elif kind == "gps":
            driver.deliver("gps/fix", navsat_msg(clock, op))
        else:
            driver.control(op)
        check_h2o_held(driver)
    driver.note_unexpected(node.rejected)
    return driver.outcome


def check_h2o_held(driver: NodeDriver) -> None:
    """Everything the mapper holds is finite."""
    mapper = driver.node.mapper
    held = {
        "graph poses": mapper.poses() if mapper.num_nodes else np.zeros((0, 3)),
        "odometry track": mapper.track.poses(),
        "keyframe odometry": np.asarray(mapper.keyframes.odom, dtype=float),
        "map_to_odom": mapper.map_to_odom(),
    }
    for name, values in held.items():
        if not np.all(np.isfinite(values)):
            driver.outcome.non_finite.append(f"held: {name}")


# -- hybrid_vo_node -------------------------------------------------------------------------------

WIDTH, HEIGHT, FX, BASELINE = 160, 120, 100.0, 0.12

INFO = st.tuples(
    st.just("info"), st.sampled_from(["left", "right"]), STAMP,
    mostly(st.just(None), st.one_of(
        st.tuples(st.sampled_from(["k", "p", "r"]), st.integers(0, 11), WILD),
        st.tuples(st.just("size"), UINT32, UINT32),
        st.tuples(st.just("d"), st.lists(WILD, max_size=9)),
        st.tuples(st.just("model"), TEXT),
    ), one_in=4),
)

IMAGE_KIND = mostly(
    st.sampled_from(["raw", "raw", "raw", "png", "jpeg"]),
    st.one_of(
        st.tuples(st.just("raw_fields"), st.sampled_from(
            ["mono8", "mono16", "bgr8", "rgba8", "8UC3", "32FC1", "", "yuv422"]),
            mostly(st.just(None), UINT32), mostly(st.just(None), UINT32),
            mostly(st.just(None), UINT32), st.integers(-5, 5)),
        st.tuples(st.just("garbage"), st.sampled_from([b"", b"\x89PNG\r\n\x1a\n", b"\xff\xd8"]),
                  st.binary(max_size=64)),
        st.tuples(st.just("oversize_png"), st.integers(1, 40000), st.integers(1, 40000)),
        st.tuples(st.just("format"), TEXT),
    ), one_in=5)

PAIR = st.tuples(st.just("pair"), STAMP, st.integers(0, 2**16), IMAGE_KIND, IMAGE_KIND)
SINGLE = st.tuples(st.just("image"), st.sampled_from(["left", "right"]), STAMP,
                   st.integers(0, 2**16), IMAGE_KIND)
WHEEL = st.tuples(st.just("wheel"), STAMP, POSE, COV6)
VO_SERVICE = st.one_of(st.just(("service", "reset")), st.tuples(st.just("pause"), st.booleans()))

#: A frame of the driving robot: a wheel step, then a good stereo pair at its stamp.
FRAME = st.tuples(st.just("frame"), st.floats(0.0, 0.2), st.floats(-0.1, 0.1),
                  mostly(st.just(7), st.integers(0, 2**16), one_in=4))
#: One ``hybrid_vo_node`` operation: frames, wheel odometry and stereo pairs (most), camera
#: info, single images, the timer, services.
VO_OP = st.one_of(FRAME, FRAME, STEP, WHEEL, PAIR, PAIR, INFO, SINGLE, TIMER, VO_SERVICE)
VO_OPS = st.lists(VO_OP, min_size=1, max_size=40)


def make_vo_node(context: Context) -> HybridVoNode:
    """A ``hybrid_vo_node`` with a debug image (so that path is fuzzed too)."""
    tag = uuid.uuid4().hex[:8]
    return HybridVoNode(f"vo_{tag}", namespace=f"/fuzz{tag}", context=context,
                        parameter_overrides=[Parameter("publish_debug_image", value=True),
                                             Parameter("camera_pitch", value=0.03)])


def camera_info_msg(clock: Clock, op: tuple[Any, ...]) -> CameraInfo:
    """A 160×120 rectified stereo calibration, possibly with one field broken."""
    _, side, stamp, mutation = op
    msg = CameraInfo(width=WIDTH, height=HEIGHT, distortion_model="plumb_bob")
    clock.stamp(msg.header.stamp, stamp)
    msg.header.frame_id = f"{side}_optical"
    k = [FX, 0.0, WIDTH / 2, 0.0, FX, HEIGHT / 2, 0.0, 0.0, 1.0]
    p = [FX, 0.0, WIDTH / 2, -FX * BASELINE if side == "right" else 0.0,
         0.0, FX, HEIGHT / 2, 0.0, 0.0, 0.0, 1.0, 0.0]
    r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    arrays = {"k": k, "p": p, "r": r}
    msg.d = [0.0] * 5
    if mutation is not None:
        what = mutation[0]
        if what in arrays:
            values = arrays[what]
            values[mutation[1] % len(values)] = float(mutation[2])
        elif what == "size":
            msg.width, msg.height = mutation[1], mutation[2]
        elif what == "d":
            msg.d = [float(v) for v in mutation[1]]
        else:
            msg.distortion_model = mutation[1]
    msg.k, msg.p, msg.r = k, p, r
    return msg


def _texture(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (HEIGHT // 4, WIDTH // 4), dtype=np.uint8)
    return cv2.resize(small, (WIDTH, HEIGHT), interpolation=cv2.INTER_LINEAR)


def _oversize_png(width: int, height: int) -> bytes:
    def chunk(kind: bytes, body: bytes) -> bytes:
        return (struct.pack(">I", len(body)) + kind + body
                + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF))

    rows = zlib.compress(b"".join(b"\x00" + bytes(min(width, 4096)) for _ in range(8)))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0,
                                                              0, 0, 0))
            + chunk(b"IDAT", rows) + chunk(b"IEND", b""))


def image_msg(clock: Clock, stamp: Any, seed: int, kind: Any, side: str) -> Any:
    """An ``Image`` or ``CompressedImage`` of an ``IMAGE_KIND`` draw."""
    pixels = _texture(seed)  # the same on both sides: a scene at infinity
    name = kind if isinstance(kind, str) else kind[0]
    if name in ("png", "jpeg", "garbage", "oversize_png", "format"):
        msg: Any = CompressedImage(format="mono8; png compressed mono8")
        if name in ("png", "jpeg", "format"):
            ok, buf = cv2.imencode(".png" if name != "jpeg" else ".jpg", pixels)
            assert ok
            msg.data = buf.tobytes()
            msg.format = {"png": msg.format, "jpeg": "mono8; jpeg compressed mono8"}.get(
                name, kind[1] if name == "format" else msg.format)
        elif name == "garbage":
            msg.data = kind[1] + kind[2]
        else:
            msg.data = _oversize_png(kind[1], kind[2])
    else:
        msg = Image(height=HEIGHT, width=WIDTH, encoding="mono8", step=WIDTH,
                    data=pixels.tobytes())
        if name == "raw_fields":
            _, encoding, height, width, step, extra = kind
            msg.encoding = encoding
            msg.height = HEIGHT if height is None else height
            msg.width = WIDTH if width is None else width
            msg.step = WIDTH if step is None else step
            data = pixels.tobytes()
            msg.data = data[: len(data) + extra] if extra < 0 else data + bytes(extra)
    clock.stamp(msg.header.stamp, stamp)
    msg.header.frame_id = f"{side}_optical"
    return msg


def run_vo(driver: NodeDriver, ops: list[tuple[Any, ...]]) -> Outcome:
    """Feed ``ops`` to a ``hybrid_vo_node`` driver; returns what it saw."""
    node: HybridVoNode = driver.node
    clock = driver.clock
    warm_up: list[tuple[Any, ...]] = [("info", "left", ("dt", 0), None),
                                      ("info", "right", ("dt", 0), None)]
    warm_up += [("frame", 0.1, 0.02, 7)] * 4
    for op in warm_up + list(ops):
        kind = op[0]
        if kind == "frame":
            driver.deliver("odom", step_msg(driver, op[1], op[2]))
            stamp = ("abs", *divmod(clock.ns, 10**9))
            for side in ("left", "right"):
                driver.deliver(f"{side}/image_rect", image_msg(clock, stamp, op[3], "raw", side))
        elif kind == "step":
            driver.deliver("odom", step_msg(driver, op[1], op[2]))
        elif kind == "wheel":
            driver.deliver("odom", odometry_msg(clock, op[1], op[2], op[3]))
        elif kind == "info":
            driver.deliver(f"{op[1]}/camera_info", camera_info_msg(clock, op))
        elif kind == "pair":
            _, stamp, seed, left_kind, right_kind = op
            left = image_msg(clock, stamp, seed, left_kind, "left")
            right = image_msg(clock, ("abs", left.header.stamp.sec, left.header.stamp.nanosec),
                              seed, right_kind, "right")
            driver.deliver("left/image_rect", left)
            driver.deliver("right/image_rect", right)
        elif kind == "image":
            _, side, stamp, seed, image_kind = op
            driver.deliver(f"{side}/image_rect", image_msg(clock, stamp, seed, image_kind, side))
        else:
            driver.control(op)
        check_vo_held(driver)
    driver.note_unexpected(node.frontend.stats.rejected)
    return driver.outcome


def check_vo_held(driver: NodeDriver) -> None:
    """The odometer's track and wheel buffer are finite."""
    frontend = driver.node.frontend
    track = frontend._track
    if track is not None and not (all(math.isfinite(v) for v in (*track.pose, *track.wheel))
                                  and np.all(np.isfinite(track.covariance))):
        driver.outcome.non_finite.append("held: odometer track")
    if not all(math.isfinite(v) for pose in frontend._wheel.poses for v in pose):
        driver.outcome.non_finite.append("held: wheel buffer")
