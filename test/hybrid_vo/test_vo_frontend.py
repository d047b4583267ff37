"""hybrid_vo.frontend and hybrid_vo.sync: the node's logic without ROS."""

from __future__ import annotations

import math
from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from hybrid_vo.errors import ConfigError
from hybrid_vo.frontend import (
    BAD_IMAGE,
    NO_CALIBRATION,
    FrontendConfig,
    InputRejected,
    VoFrontend,
    VoOutput,
    WheelBuffer,
    between,
    compose,
    reason_key,
)
from hybrid_vo.odometer import HybridOdometer
from hybrid_vo.sim.messages import camera_models
from hybrid_vo.sim.world import Drive, make_drive, scenario, wrap_angle
from hybrid_vo.sync import LEFT, RIGHT, StarvationMonitor, StereoSync, SyncConfig
from msg_adapters import AdapterError

MS = 1_000_000
TURN = (math.pi / 2) / 3.0
PITCH = 0.03  # the simulated drives' camera pitch


@cache
def _drive(name: str, seconds: float) -> Drive:
    if name == "slip":
        # The first 18 s of the slip scenario: heading drift 4–14 s, a false 0.4 rad turn at 8 s.
        segments = ((6.0, 1.3, 0.0), (3.0, 1.0, TURN), (6.0, 1.3, 0.0), (3.0, 1.0, TURN))
        return make_drive(scenario("slip", segments=segments))
    return make_drive(scenario("straight", segments=((seconds, 1.3, 0.0),)))


@cache
def _frames(name: str, seconds: float) -> list:
    return list(_drive(name, seconds).frames())


def _frontend(drive: Drive | None = None, **kwargs) -> VoFrontend:
    fe = VoFrontend(FrontendConfig(camera_pitch=PITCH, **kwargs))
    if drive is not None:
        fe.set_calibration(*camera_models(drive, 0))
    return fe


def _feed(fe: VoFrontend, drive: Drive, frames: list, wheel_first: bool = True) -> list[VoOutput]:
    wheel = drive.wheel_poses()
    outputs: list[VoOutput] = []
    for i, frame in enumerate(frames):
        stamp = int(drive.stamps_ns[i])
        if wheel_first:
            outputs += fe.add_wheel(stamp, *wheel[i])
        outputs += fe.add_frame(stamp, frame.left, frame.right)
        if not wheel_first:
            outputs += fe.add_wheel(stamp, *wheel[i])
    return outputs


# ----------------------------------------------------------------------------- wheel buffer


def test_wheel_buffer_interpolates_position_and_shortest_yaw_arc() -> None:
    buf = WheelBuffer(keep_s=10.0)
    buf.add(0, (0.0, 0.0, math.pi - 0.1))
    buf.add(100 * MS, (1.0, 2.0, -math.pi + 0.1))  # crossed ±π: the arc is 0.2 rad, not 6.08
    x, y, yaw = buf.at(25 * MS)
    assert (x, y) == pytest.approx((0.25, 0.5))
    assert yaw == pytest.approx(math.pi - 0.05)
    assert buf.at(100 * MS) == (1.0, 2.0, -math.pi + 0.1)
    assert buf.at(101 * MS) is None  # not covered yet
    assert buf.at(-1) is None  # before the first sample
    assert buf.covers(100 * MS) and not buf.covers(100 * MS + 1)


def test_wheel_buffer_trim_keeps_what_the_horizon_needs() -> None:
    buf = WheelBuffer(keep_s=0.25)
    for k in range(10):
        buf.add(k * 100 * MS, (float(k), 0.0, 0.0))
    buf.trim()
    # Newest 900 ms, horizon 650 ms: the sample at 600 ms stays to bracket 650 ms.
    assert buf.stamps == [600 * MS, 700 * MS, 800 * MS, 900 * MS]
    assert buf.at(650 * MS)[0] == pytest.approx(6.5)


def test_planar_compose_and_between_are_inverse() -> None:
    a = (1.0, -2.0, 3.0)
    d = (0.3, 0.1, 0.5)
    assert between(a, compose(a, d)) == pytest.approx(d)


# ----------------------------------------------------------------------------- frames


def test_frame_waits_for_wheel_odometry_then_uses_the_interpolated_increment() -> None:
    drive = _drive("straight", 1.0)
    frames = _frames("straight", 1.0)
    fe = _frontend(drive)
    assert fe.add_wheel(0, 0.0, 0.0, 0.0) == []
    first = fe.add_frame(0, frames[0].left, frames[0].right)
    assert len(first) == 1 and first[0].fallback == "first_frame"
    assert first[0].pose == (0.0, 0.0, 0.0)
    # A frame at 100 ms waits: the wheels have only reached 0 ms.
    assert fe.add_frame(100 * MS, frames[1].left, frames[1].right) == []
    assert fe.pending_frames == 1
    out = fe.add_wheel(200 * MS, 0.26, 0.0, 0.02)
    assert len(out) == 1 and fe.pending_frames == 0
    assert out[0].wheel_delta == pytest.approx((0.13, 0.0, 0.01))
    assert out[0].stamp_ns == 100 * MS
    assert out[0].v_x_mps == pytest.approx(out[0].delta[0] / 0.1)


def test_without_calibration_the_wheels_drive_and_say_why() -> None:
    drive = _drive("straight", 1.0)
    fe = _frontend()
    outputs = _feed(fe, drive, _frames("straight", 1.0))
    assert len(outputs) == len(drive)
    assert {o.fallback for o in outputs} == {NO_CALIBRATION}
    assert not any(o.used_vision for o in outputs)
    wheel = drive.wheel_poses()
    np.testing.assert_allclose(outputs[-1].pose, wheel[-1], atol=1e-9)
    assert fe.stats.fallbacks[NO_CALIBRATION] == len(drive)
    assert fe.stats.fallback_fraction == 1.0


def test_bad_and_blank_images_fall_back_and_tracking_resumes() -> None:
    drive = _drive("straight", 1.0)
    frames = _frames("straight", 1.0)
    fe = _frontend(drive)
    wheel = drive.wheel_poses()
    blank = np.full_like(frames[0].left, 128)
    fallbacks = []
    for i, frame in enumerate(frames):
        stamp = int(drive.stamps_ns[i])
        fe.add_wheel(stamp, *wheel[i])
        if i == 3:
            (out,) = fe.add_frame(stamp, None, None)  # e.g. undecodable
        elif i == 4:
            (out,) = fe.add_frame(stamp, frame.left[:50], frame.right)  # wrong size
        elif i in (6, 7):
            (out,) = fe.add_frame(stamp, blank, blank)  # lens cap
        else:
            (out,) = fe.add_frame(stamp, frame.left, frame.right)
        fallbacks.append(out.fallback)
        assert np.all(np.isfinite(out.pose)) and np.all(np.isfinite(out.covariance))
    assert fallbacks[3] == BAD_IMAGE and fallbacks[4] == BAD_IMAGE
    assert fallbacks[5] == "first_frame"  # tracking restarts after an unusable frame
    assert fallbacks[7] == "blank_view"
    assert fallbacks[9] == "none"
    assert fe.stats.rejected[BAD_IMAGE] == 1  # the wrong-size frame; None was refused upstream
    np.testing.assert_allclose(fe.stats.vision_frames, fallbacks.count("none"))


def test_time_going_backwards_is_rejected_counted_and_harmless() -> None:
    drive = _drive("straight", 1.0)
    frames = _frames("straight", 1.0)
    fe = _frontend(drive)
    outputs = _feed(fe, drive, frames[:5])
    last = outputs[-1]
    with pytest.raises(InputRejected, match="frame_time_backwards"):
        fe.add_frame(int(drive.stamps_ns[2]), frames[2].left, frames[2].right)
    with pytest.raises(InputRejected, match="frame_time_backwards"):  # equal stamps too
        fe.add_frame(int(drive.stamps_ns[4]), frames[4].left, frames[4].right)
    with pytest.raises(InputRejected, match="wheel_time_backwards"):
        fe.add_wheel(int(drive.stamps_ns[1]), 0.0, 0.0, 0.0)
    with pytest.raises(InputRejected, match="wheel_not_finite"):
        fe.add_wheel(int(drive.stamps_ns[9]), math.nan, 0.0, 0.0)
    assert fe.stats.rejected == {
        "frame_time_backwards": 2,
        "wheel_time_backwards": 1,
        "wheel_not_finite": 1,
    }
    assert fe.stats.frames == 5
    # Nothing accepted was lost: the drive continues from where it was.
    wheel = drive.wheel_poses()
    fe.add_wheel(int(drive.stamps_ns[5]), *wheel[5])
    (out,) = fe.add_frame(int(drive.stamps_ns[5]), frames[5].left, frames[5].right)
    assert out.used_vision
    assert between(last.pose, out.pose)[0] == pytest.approx(0.13, abs=0.01)


def test_frames_before_the_wheel_data_and_overflowing_frames_are_counted() -> None:
    drive = _drive("straight", 1.0)
    frames = _frames("straight", 1.0)
    fe = _frontend(drive, max_pending_frames=2)
    for i in range(4):  # no wheel odometry yet: two wait, the two oldest are dropped
        assert fe.add_frame(int(drive.stamps_ns[i]), frames[i].left, frames[i].right) == []
    assert fe.pending_frames == 2 and fe.stats.rejected["frame_wheel_timeout"] == 2
    # Wheel data that starts after both waiting frames: they cannot be interpolated.
    assert fe.add_wheel(int(drive.stamps_ns[5]), 0.0, 0.0, 0.0) == []
    assert fe.stats.rejected["frame_not_covered_by_wheel"] == 2
    assert "older than the buffered wheel odometry" in fe.stats.last_rejection


def test_reset_restarts_at_a_pose_and_accepts_earlier_stamps() -> None:
    drive = _drive("straight", 1.0)
    frames = _frames("straight", 1.0)
    fe = _frontend(drive)
    _feed(fe, drive, frames)
    fe.reset((5.0, -1.0, 0.5))
    outputs = _feed(fe, drive, frames[:4])  # a replay from the start
    assert outputs[0].pose == (5.0, -1.0, 0.5)
    np.testing.assert_allclose(outputs[0].covariance, np.eye(3) * 1e-6)
    assert outputs[0].fallback == "first_frame"
    assert all(o.used_vision for o in outputs[1:])
    assert outputs[-1].x_m == pytest.approx(5.0 + 3 * 0.13 * math.cos(0.5), abs=0.02)
    assert fe.stats.frames == len(drive) + 4  # counters survive a reset


def test_pause_drops_frames_and_resume_keeps_odom_continuous() -> None:
    drive = _drive("straight", 2.0)
    frames = _frames("straight", 2.0)
    fe = _frontend(drive)
    wheel = drive.wheel_poses()
    outputs = _feed(fe, drive, frames[:5])
    fe.pause()
    assert fe.paused
    for i in range(5, 10):
        fe.add_wheel(int(drive.stamps_ns[i]), *wheel[i])
        assert fe.add_frame(int(drive.stamps_ns[i]), frames[i].left, frames[i].right) == []
    assert fe.stats.dropped_paused == 5
    fe.resume()
    fe.add_wheel(int(drive.stamps_ns[10]), *wheel[10])
    (out,) = fe.add_frame(int(drive.stamps_ns[10]), frames[10].left, frames[10].right)
    assert out.fallback == "first_frame"  # tracking restarts after a pause
    # The wheel motion made while paused is added: odom does not jump.
    assert out.wheel_delta == pytest.approx(between(tuple(wheel[4]), tuple(wheel[10])))
    assert out.pose == pytest.approx(compose(outputs[-1].pose, out.wheel_delta))


def test_covariance_grows_and_stays_symmetric_positive_definite() -> None:
    drive = _drive("straight", 2.0)
    outputs = _feed(_frontend(drive), drive, _frames("straight", 2.0))
    yaw_var = [o.covariance[2, 2] for o in outputs]
    xy_var = [o.covariance[0, 0] + o.covariance[1, 1] for o in outputs]
    assert all(b > a for a, b in zip(yaw_var, yaw_var[1:], strict=False))
    assert all(b > a for a, b in zip(xy_var, xy_var[1:], strict=False))
    for o in outputs:
        np.testing.assert_allclose(o.covariance, o.covariance.T)
        assert np.linalg.eigvalsh(o.covariance)[0] > 0.0
        full = o.covariance_6x6
        assert full.shape == (6, 6) and full[2, 2] == full[3, 3] == full[4, 4] == 1e6
        assert full[5, 5] == o.covariance[2, 2] and full[0, 5] == o.covariance[0, 2]


def test_slip_drive_heading_error_is_a_small_fraction_of_the_wheels() -> None:
    drive = _drive("slip", 0.0)
    frames = _frames("slip", 0.0)
    fe = _frontend(drive)
    outputs = _feed(fe, drive, frames, wheel_first=False)  # frames wait for the wheels
    assert len(outputs) == len(drive) and fe.pending_frames == 0
    yaw = np.array([o.yaw_rad for o in outputs])
    wheel = drive.wheel_poses()
    err_vo = np.abs(wrap_angle(yaw - drive.truth[:, 2]))
    err_wheel = np.abs(wrap_angle(wheel[:, 2] - drive.truth[:, 2]))
    assert err_wheel.max() > 0.5  # the wheels drifted and hallucinated a turn
    rms_vo = math.sqrt(float(np.mean(err_vo**2)))
    rms_wheel = math.sqrt(float(np.mean(err_wheel**2)))
    assert rms_vo < 0.2 * rms_wheel
    assert err_vo.max() < 0.2 * err_wheel.max()
    assert fe.stats.fallback_fraction < 0.1
    # The frontend adds nothing of its own: the odometer driven directly gives the same path.
    odo = HybridOdometer(drive.camera_info.intrinsics, drive.camera_info.mounting)
    direct = np.array([odo.process(f, drive.wheel_deltas[i]).pose for i, f in enumerate(frames)])
    np.testing.assert_allclose(yaw, direct[:, 2], atol=1e-9)
    image = fe.debug_image(scale=2)
    assert image is not None and image.dtype == np.uint8
    assert image.shape == tuple(2 * n for n in fe.odometer.spherical.shape)
    assert image.max() == 255  # patch boxes are drawn


# ----------------------------------------------------------------------------- calibration


def test_calibration_is_checked_and_the_odometer_rebuilt_only_when_it_changes() -> None:
    drive = _drive("straight", 1.0)
    left, right = camera_models(drive, 0)
    fe = _frontend()
    assert not fe.calibrated
    with pytest.raises(InputRejected, match="calibration.*baseline"):
        fe.set_calibration(left, left)  # the left info twice: no baseline
    assert not fe.calibrated and fe.stats.rejected["calibration"] == 1
    assert fe.set_calibration(left, right)
    odometer = fe.odometer
    assert odometer is not None and odometer.mounting.baseline_m == pytest.approx(0.12)
    assert odometer.mounting.pitch_rad == PITCH
    assert not fe.set_calibration(*camera_models(drive, 10**9))  # same calibration
    wider = replace(right, P=right.P * np.array([[1.0, 1.0, 1.0, 2.0]] * 3))
    assert fe.set_calibration(left, wider)
    assert fe.odometer is not odometer and fe.odometer.mounting.baseline_m == pytest.approx(0.24)
    assert fe.stats.calibrations == 2


def test_a_mounting_that_hides_the_horizon_is_rejected_at_calibration() -> None:
    drive = _drive("straight", 1.0)
    fe = VoFrontend(FrontendConfig(camera_pitch=1.2))  # looking at the ground
    with pytest.raises(InputRejected, match="horizon band"):
        fe.set_calibration(*camera_models(drive, 0))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"wheel_buffer": 0.0}, "wheel_buffer"),
        ({"max_pending_frames": 0}, "max_pending_frames"),
        ({"camera_height": -1.0}, "height_m"),
        ({"camera_pitch": 2.0}, "pitch_rad"),
    ],
)
def test_bad_config_fails_at_construction(kwargs, match) -> None:
    with pytest.raises(ConfigError, match=match):
        FrontendConfig(**kwargs)


def test_reason_keys_name_source_field_and_problem_without_values() -> None:
    assert reason_key("odom", AdapterError("Odometry.pose.pose.orientation: zero quaternion")) \
        == "odom: Odometry.pose.pose.orientation: zero quaternion"
    assert reason_key("left_image", AdapterError(
        "Image: size 100x100 differs from the expected 160x120")) == "left_image: Image: size"
    assert reason_key("left_image", AdapterError(
        "Image.encoding: unsupported 'rgb9' (supported: mono8)")) \
        == "left_image: Image.encoding: unsupported"
    assert reason_key("x", AdapterError("plain")) == "x: plain"


# ----------------------------------------------------------------------------- sync


def test_exact_sync_pairs_equal_stamps_only() -> None:
    sync: StereoSync[str] = StereoSync(SyncConfig(approx_sync=False))
    assert sync.add(LEFT, 100, "l1") is None
    assert sync.add(RIGHT, 101, "r1") is None
    pair = sync.add(RIGHT, 100, "r0")
    assert pair is not None and (pair.stamp_ns, pair.left, pair.right) == (100, "l1", "r0")
    assert sync.queued(LEFT) == 0 and sync.queued(RIGHT) == 1


def test_approx_sync_pairs_nearest_within_the_interval_and_drops_the_rest() -> None:
    sync: StereoSync[str] = StereoSync(SyncConfig(approx_sync_max_interval=0.005))
    assert sync.add(LEFT, 0, "l0") is None
    assert sync.add(LEFT, 100 * MS, "l1") is None
    assert sync.add(RIGHT, 50 * MS, "r-far") is None  # 50 ms from either: no pair
    pair = sync.add(RIGHT, 103 * MS, "r1")
    assert pair is not None and (pair.stamp_ns, pair.left, pair.right) == (100 * MS, "l1", "r1")
    # l0 and r-far can never pair now: dropped and counted.
    assert sync.stats.dropped == [1, 1] and sync.stats.pairs == 1
    assert sync.queued(LEFT) == sync.queued(RIGHT) == 0
    pair = sync.add(LEFT, 197 * MS, "l2") or sync.add(RIGHT, 200 * MS, "r2")
    assert pair is not None and pair.stamp_ns == 197 * MS and sync.stats.last_pair_ns == 197 * MS


def test_sync_queue_is_bounded() -> None:
    sync: StereoSync[int] = StereoSync(SyncConfig(sync_queue_size=3))
    for k in range(5):
        assert sync.add(LEFT, k * 100 * MS, k) is None
    assert sync.queued(LEFT) == 3 and sync.stats.dropped[LEFT] == 2
    sync.clear()
    assert sync.queued(LEFT) == 0


def test_bad_sync_config_is_refused() -> None:
    with pytest.raises(ConfigError, match="sync_queue_size"):
        SyncConfig(sync_queue_size=0)
    with pytest.raises(ConfigError, match="approx_sync_max_interval"):
        SyncConfig(approx_sync_max_interval=math.nan)


def test_starvation_monitor_names_the_quiet_topic_and_the_one_that_arrives() -> None:
    mon = StarvationMonitor(timeout_s=2.0)
    mon.watch("/left/image_rect", partner="/right/image_rect")
    mon.watch("/right/image_rect", partner="/left/image_rect")
    mon.watch("/left/camera_info", once=True)
    mon.watch("/odom")
    for k in range(31):  # 3 s of left images at 10 Hz; right stops after 0.5 s
        mon.note("/left/image_rect", k * 100 * MS)
        mon.note("/odom", k * 50 * MS + 10**8)  # arrives faster, but is not the partner
        if k <= 5:
            mon.note("/right/image_rect", k * 100 * MS)
    assert mon.rate_hz("/left/image_rect") == pytest.approx(10.0)
    assert mon.starving() == [
        "no /right/image_rect for 2.5 s while /left/image_rect arrives at 10 Hz",
        "no /left/camera_info for 3.0 s while /odom arrives at 20 Hz",
    ]
    mon.note("/left/camera_info", 3000 * MS)  # once is enough for a camera info
    mon.note("/right/image_rect", 3000 * MS)
    assert mon.starving() == []
    mon.note("/unwatched", 10**12)  # ignored
    assert mon.starving() == []
    mon.reset()
    assert mon.starving() == [] and mon.rate_hz("/left/image_rect") == 0.0
