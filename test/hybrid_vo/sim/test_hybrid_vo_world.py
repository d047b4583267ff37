"""The synthetic stereo world: determinism, speed, and the sensor records."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from h2o_slam.core.geometry import planar_between
from hybrid_vo.errors import ConfigError
from hybrid_vo.sim.world import (
    STATUS_FIX,
    STATUS_NO_FIX,
    DriveConfig,
    NearObject,
    WheelSlipConfig,
    World,
    WorldConfig,
    make_drive,
    scenario,
    wrap_angle,
)


def test_deterministic_from_seed() -> None:
    cfg = DriveConfig(segments=((3.0, 1.3, 0.1),), seed=3)
    a, b = make_drive(cfg), make_drive(cfg)
    c = make_drive(DriveConfig(segments=((3.0, 1.3, 0.1),), seed=4))
    np.testing.assert_array_equal(a.frame(7).left, b.frame(7).left)
    np.testing.assert_array_equal(a.wheel_deltas, b.wheel_deltas)
    assert not np.array_equal(a.frame(7).left, c.frame(7).left)


def test_renders_a_few_hundred_frames_in_seconds() -> None:
    drive = make_drive(DriveConfig(segments=((30.0, 1.3, 0.05),), num_objects=10))
    start = time.perf_counter()
    for frame in drive.frames():
        assert frame.left.shape == (120, 160) and frame.left.dtype == np.uint8
    assert len(drive) == 301  # the start pose plus one per step
    # About 1.5 s on an idle core; the bound leaves room for a loaded CI machine.
    assert time.perf_counter() - start < 8.0


def test_objects_at_the_edge_of_the_view_are_drawn() -> None:
    # The renderer skips objects outside the horizontal field of view and culls pixels by
    # bearing; an object straddling the image's side must still show up, cut by the edge.
    cfg = DriveConfig(segments=((1.0, 0.0, 0.0),), num_objects=0)
    drive = make_drive(cfg)
    info = drive.camera_info
    half_fov = math.atan(info.intrinsics.cx_px / info.intrinsics.fx_px)
    for side in (1.0, -1.0):
        post = NearObject(4.0 * math.cos(half_fov), side * 4.0 * math.sin(half_fov), 0.3, 3.0)
        world = World(drive.world.config, (post,), info.intrinsics, info.mounting)
        left, _ = world.render_stereo(np.zeros(3), 0)
        bare, _ = drive.world.render_stereo(np.zeros(3), 0)
        changed = np.nonzero(np.any(left != bare, axis=0))[0]
        edge = 0 if side > 0 else info.intrinsics.width_px - 1
        assert edge in changed  # the post runs off the image on its side
        assert 3 < changed.size < info.intrinsics.width_px // 4


def test_stereo_pair_has_the_baseline_disparity() -> None:
    drive = make_drive(DriveConfig(segments=((1.0, 1.0, 0.0),), num_objects=0))
    frame = drive.frame(0)
    # Ground 3 m ahead (row below the horizon): disparity fx·B/z in the rectified pair.
    fx, base = drive.camera_info.intrinsics.fx_px, drive.camera_info.mounting.baseline_m
    p = drive.camera_info.projection_right()
    assert p[0, 3] == pytest.approx(-fx * base)
    assert not np.array_equal(frame.left, frame.right)


def test_wheel_slip_hallucinated_turn_and_drift() -> None:
    slip = WheelSlipConfig(
        scale_sigma=0.0,
        yaw_sigma_rad_per_sqrt_m=0.0,
        drift_rate_rad_s=0.1,
        drift_windows_s=((1.0, 2.0),),
        hallucinated_turns=((3.0, 0.4, 0.5),),
    )
    drive = make_drive(DriveConfig(segments=((5.0, 1.0, 0.0),), slip=slip, num_objects=0))
    extra = drive.wheel_deltas[:, 2] - drive.true_deltas[:, 2]
    assert extra.sum() == pytest.approx(0.1 * 1.0 + 0.4)
    assert extra[30:35].sum() == pytest.approx(0.4)
    # Truth itself is straight.
    assert np.abs(drive.truth[:, 2]).max() == 0.0


def test_gps_has_noise_dropouts_and_geodetic_fields() -> None:
    drive = make_drive(
        DriveConfig(segments=((200.0, 1.0, 0.0),), num_objects=0, gps_dropout=0.3, gps_sigma_m=2.0)
    )
    fixes = drive.gps
    assert len(fixes) == 201
    lost = [f for f in fixes if f.status == STATUS_NO_FIX]
    good = [f for f in fixes if f.status == STATUS_FIX]
    assert 30 < len(lost) < 90
    assert all(math.isnan(f.latitude_deg) for f in lost)
    idx = (np.array([f.stamp_ns for f in good]) // 100_000_000).astype(int)
    err = np.array([f.east_m for f in good]) - drive.truth[idx, 0]
    assert np.std(err) == pytest.approx(2.0, rel=0.25)
    assert good[0].covariance_enu[0] == pytest.approx(4.0)
    assert all(abs(f.latitude_deg - 37.4275) < 0.01 for f in good)


def test_loop_closures_where_the_path_revisits_itself() -> None:
    drive = make_drive(scenario("loop", num_objects=0))
    assert len(drive.loop_closures) >= 2
    for lc in drive.loop_closures:
        truth = planar_between(drive.truth[lc.from_index], drive.truth[lc.to_index])
        assert lc.to_index - lc.from_index >= 100
        assert np.hypot(truth[0], truth[1]) < 2.0
        np.testing.assert_allclose(lc.delta[:2], truth[:2], atol=0.3)
        assert abs(float(wrap_angle(lc.delta[2] - truth[2]))) < 0.05
    # The rounded square returns to its start.
    assert np.hypot(*drive.truth[len(drive) // 2, :2]) < 1.0


def test_objects_keep_clear_of_the_path() -> None:
    drive = make_drive(scenario("cluttered"))
    assert len(drive.world.objects) >= 40
    for obj in drive.world.objects:
        gap = np.min(np.hypot(drive.truth[:, 0] - obj.x_m, drive.truth[:, 1] - obj.y_m))
        assert gap - obj.radius_m >= 0.8


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: DriveConfig(segments=()), "at least one segment"),
        (lambda: DriveConfig(segments=((-1.0, 1.0, 0.0),)), "duration"),
        (lambda: DriveConfig(gps_dropout=2.0), "gps_dropout"),
        (lambda: WheelSlipConfig(hallucinated_turns=((1.0, 0.3, 0.0),)), "duration"),
        (lambda: WorldConfig(far_radius_m=1.0), "far_radius_m"),
        (lambda: scenario("moon"), "unknown scenario"),
    ],
)
def test_bad_world_config_raises(make, match) -> None:
    with pytest.raises(ConfigError, match=match):
        make()


def test_gps_fixes_convert_back_to_their_enu_exactly() -> None:
    # The fixes' latitude/longitude are exact WGS-84 images of their ENU positions about
    # GPS_DATUM, as the node converts them back (msg_adapters.gps).
    from hybrid_vo.sim import world
    from msg_adapters.gps import Datum

    drive = world.make_drive(world.scenario("straight", seed=1))
    datum = Datum(*world.GPS_DATUM)
    good = [f for f in drive.gps if f.status == world.STATUS_FIX]
    enu = datum.to_enu(np.array([f.latitude_deg for f in good]),
                       np.array([f.longitude_deg for f in good]),
                       np.array([f.altitude_m for f in good]))
    want = np.array([[f.east_m, f.north_m, f.up_m] for f in good])
    np.testing.assert_allclose(enu, want, atol=1e-6)
