"""The hybrid odometer end to end on the synthetic world: range test, fallbacks, slip."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from hybrid_vo import patches as pt
from hybrid_vo.camera import CameraIntrinsics, CameraMounting
from hybrid_vo.errors import ConfigError, FrameError
from hybrid_vo.frames import StereoFrame
from hybrid_vo.odometer import FallbackReason, HybridOdometer, OdometerConfig
from hybrid_vo.sim.world import (
    DriveConfig,
    NearObject,
    WheelSlipConfig,
    World,
    WorldConfig,
    make_drive,
    wrap_angle,
)

INTR = CameraIntrinsics(160, 120, 125.0, 125.0, 79.5, 59.5)
MOUNT = CameraMounting(pitch_rad=0.03, height_m=1.0, baseline_m=0.12)
STEP = np.array([0.13, 0.0, 0.0])  # 1.3 m/s at 10 Hz, straight ahead


def _two_frames(
    objects: tuple[NearObject, ...], seed: int = 1, intr: CameraIntrinsics = INTR
) -> list[StereoFrame]:
    world = World(WorldConfig(seed=seed), objects, intr, MOUNT)
    frames = []
    for i, x in enumerate((0.0, 0.13)):
        left, right = world.render_stereo(np.array([x, 0.0, 0.0]), i)
        frames.append(StereoFrame(left, right, i * 100_000_000))
    return frames


def _run(frames: list[StereoFrame], odo: HybridOdometer | None = None):
    odo = odo or HybridOdometer(INTR, MOUNT)
    first = odo.process(frames[0], np.zeros(3))
    assert first.fallback is FallbackReason.FIRST_FRAME
    return odo, odo.process(frames[1], STEP)


def test_r_min_is_equation_2_3_at_theta_max() -> None:
    odo = HybridOdometer(INTR, MOUNT)
    cfg = odo.config
    assert cfg.max_travel_m == pytest.approx(0.13)  # d = 1.3 m/s / 10 Hz
    assert odo.theta_max_rad == pytest.approx(0.14)  # thesis' value; camera side is farther
    a = odo.spherical.a_rad_per_px
    assert odo.r_min_m == pytest.approx(pt.r_min_m(0.13, odo.theta_max_rad, a))


def test_open_view_tracks_with_all_patches() -> None:
    _, upd = _run(_two_frames(()))
    assert upd.fallback is FallbackReason.NONE
    assert upd.num_sampled == 6 and upd.num_far == 6 and upd.num_inliers >= 5
    assert abs(upd.dyaw_rad) < 0.004  # straight drive: half a spherical pixel
    assert 0 < upd.yaw_sigma_rad < 0.01


@pytest.mark.parametrize(("range_factor", "kept"), [(0.6, False), (2.0, True)])
@pytest.mark.parametrize("input_width", [160, 640])
def test_near_features_are_dropped_by_equation_2_3(range_factor, kept, input_width) -> None:
    # At 640 px the range comes from the pair as it arrived (stereo_at_input_resolution).
    intr = INTR.scaled(input_width, input_width * 3 // 4)
    odo = HybridOdometer(intr, MOUNT)
    dist = range_factor * odo.r_min_m
    # A textured column straight ahead, wide enough to fill the sampling region ±θ_max.
    radius = dist * math.sin(odo.theta_max_rad + 0.08)
    wall = NearObject(dist + radius + 0.13, 0.0, radius, 6.0)
    _, upd = _run(_two_frames((wall,), intr=intr), odo)
    assert upd.num_sampled >= 3
    if kept:
        assert upd.num_far == upd.num_sampled
        assert upd.fallback is FallbackReason.NONE
    else:
        # The view is blocked by a near object: every patch fails (2.3), the wheels step in.
        assert upd.num_far < 3
        assert upd.fallback is FallbackReason.NEAR_FEATURES
        np.testing.assert_allclose(upd.delta, STEP)
        assert odo.stats.by_reason == {"first_frame": 1, "near_features": 1}


def test_blank_view_falls_back_to_wheel_odometry_and_says_so() -> None:
    blank = np.full((120, 160), 128, np.uint8)
    frames = [StereoFrame(blank, blank, 0), StereoFrame(blank, blank, 100)]
    odo, upd = _run(frames)
    assert upd.fallback is FallbackReason.BLANK_VIEW
    assert not upd.used_vision
    np.testing.assert_allclose(upd.delta, STEP)
    assert upd.yaw_sigma_rad == odo.config.fallback_yaw_sigma_rad
    assert odo.stats.deferred == 2 and odo.stats.deferred_fraction == 1.0
    assert odo.stats.cpu_time_total_s >= 0.0


def _slip_drive() -> DriveConfig:
    slip = WheelSlipConfig(
        drift_rate_rad_s=0.04,
        drift_windows_s=((2.0, 20.0),),
        hallucinated_turns=((4.0, 0.4, 0.8), (13.0, -0.5, 1.0), (19.0, 0.35, 0.6)),
    )
    segments = ((8.0, 1.3, 0.0), (5.0, 1.0, 0.3), (9.0, 1.3, 0.0))
    return DriveConfig(name="hallucinated", seed=4, segments=segments, slip=slip, num_objects=8)


def test_hallucinated_turns_barely_move_the_hybrid_heading() -> None:
    drive = make_drive(_slip_drive())
    odo = HybridOdometer(drive.camera_info.intrinsics, drive.camera_info.mounting)
    poses = np.array(
        [odo.process(f, drive.wheel_deltas[i]).pose for i, f in enumerate(drive.frames())]
    )
    wheel = drive.wheel_poses()
    err_hybrid = np.abs(wrap_angle(poses[:, 2] - drive.truth[:, 2]))
    err_wheel = np.abs(wrap_angle(wheel[:, 2] - drive.truth[:, 2]))
    assert err_wheel.max() > 0.5  # the wheels hallucinated turns worth half a radian
    rmse_h = math.sqrt(float(np.mean(err_hybrid**2)))
    rmse_w = math.sqrt(float(np.mean(err_wheel**2)))
    assert rmse_h < 0.1 * rmse_w
    assert err_hybrid.max() < 0.1 * err_wheel.max()
    assert odo.stats.deferred_fraction < 0.2
    assert odo.stats.frames == len(drive)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"num_patches": 0}, "num_patches"),
        ({"patch_width_px": 12}, "odd integer"),
        ({"min_patches": 9}, "cannot exceed"),
        ({"min_ncc": 1.5}, "min_ncc"),
        ({"frame_rate_hz": math.nan}, "frame_rate_hz"),
        ({"sigma_merge": "mean"}, "sigma_merge"),
        ({"work_width_px": 16}, "work_width_px"),
        ({"match_blur_px": -1.0}, "match_blur_px"),
    ],
)
def test_bad_config_raises(kwargs, match) -> None:
    with pytest.raises(ConfigError, match=match):
        OdometerConfig(**kwargs)
    with pytest.raises(ValueError):  # ConfigError is a ValueError too
        OdometerConfig(**kwargs)


def test_camera_that_does_not_see_ahead_is_rejected() -> None:
    with pytest.raises(ConfigError, match="frontal direction"):
        HybridOdometer(INTR, replace(MOUNT, yaw_rad=1.2))


def test_bad_frames_raise_and_leave_state_alone() -> None:
    odo = HybridOdometer(INTR, MOUNT)
    good = np.zeros((120, 160), np.uint8)
    with pytest.raises(FrameError, match="expected \\(120, 160\\)"):
        odo.process(StereoFrame(np.zeros((10, 10), np.uint8), good, 0), np.zeros(3))
    with pytest.raises(FrameError, match="dtype float64"):
        odo.process(StereoFrame(good.astype(float), good, 0), np.zeros(3))  # type: ignore[arg-type]
    with pytest.raises(FrameError, match="wheel_delta"):
        odo.process(StereoFrame(good, good, 0), np.array([0.1, math.nan, 0.0]))
    assert odo.stats.frames == 0


def test_posts_beside_the_path_do_not_bend_a_straight_drive() -> None:
    # Posts 4–27 m ahead on the left pass (2.3) (their parallax is under half a pixel) but a
    # sub-pixel NCC peak still sees it, always on the same side: without the correction
    # the heading bends by about 0.1 rad over 20 m of straight road.
    drive = make_drive(DriveConfig(segments=((15.0, 1.3, 0.0),), num_objects=0, seed=2))
    info = drive.camera_info
    posts = tuple(
        NearObject(4.0 + 2.5 * k, 1.2 + 0.3 * (k % 3), 0.3, 3.0, 0.1 * k) for k in range(10)
    )
    drive.world = World(drive.world.config, posts, info.intrinsics, info.mounting)
    frames = list(drive.frames())
    configs = {
        "off": OdometerConfig(parallax_correction=False),
        "on": OdometerConfig(),
        # Every post has less than 100 px of disparity: all taken as far, nothing corrected.
        "unranged": OdometerConfig(parallax_min_disparity_px=100.0),
    }
    final_yaw = {}
    for name, cfg in configs.items():
        odo = HybridOdometer(info.intrinsics, info.mounting, cfg)
        poses = [odo.process(f, drive.wheel_deltas[i]).pose for i, f in enumerate(frames)]
        assert odo.stats.deferred_fraction < 0.05
        final_yaw[name] = abs(poses[-1][2])
    assert final_yaw["off"] > 0.04
    assert final_yaw["unranged"] > 0.04
    assert final_yaw["on"] < 0.01

