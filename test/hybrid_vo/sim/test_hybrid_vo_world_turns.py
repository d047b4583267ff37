"""The synthetic drives with sharp turns (``sharp_turns``, ``spin``) of hybrid_vo.sim.world."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hybrid_vo.errors import ConfigError
from hybrid_vo.sim.world import make_drive, scenario


def test_sharp_turns_takes_right_angles_at_nine_and_eleven_degrees_a_frame():
    drive = make_drive(scenario("sharp_turns", num_objects=0))
    yaw = np.degrees(drive.true_deltas[:, 2])
    assert np.max(np.abs(yaw)) == pytest.approx(11.25, abs=1e-6)
    assert np.sum(np.isclose(yaw, 9.0)) == 30 and np.sum(np.isclose(yaw, -9.0)) == 10
    # Left 90°, right 90°, U-turn left 180°, left 90°: 270° net.
    assert math.degrees(float(np.sum(drive.true_deltas[:, 2]))) == pytest.approx(270.0)
    assert np.all(np.hypot(*drive.true_deltas[1:, :2].T) > 0.05)  # it never stops


def test_spin_turns_on_the_spot_up_to_pi_radians_a_second():
    drive = make_drive(scenario("spin", num_objects=0))
    d = drive.true_deltas[1:]
    spinning = np.abs(d[:, 2]) > 0
    assert np.allclose(np.hypot(d[spinning, 0], d[spinning, 1]), 0.0)
    assert np.max(np.abs(np.degrees(d[:, 2]))) == pytest.approx(18.0)
    assert math.degrees(float(np.sum(d[:, 2]))) == pytest.approx(360.0 - 180.0)
    # The wheels' heading noise grows with travel, so a spin on the spot reports it exactly.
    assert np.allclose(drive.wheel_deltas[1:][spinning, 2], d[spinning, 2])


def test_new_drives_render_and_are_named_in_the_error():
    frame = make_drive(scenario("spin", segments=((0.2, 0.0, math.pi),))).frame(1)
    assert frame.left.shape == (120, 160) and frame.left.std() > 5
    with pytest.raises(ConfigError, match="sharp_turns or spin"):
        scenario("moon")
