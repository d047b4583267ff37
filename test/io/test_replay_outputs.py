"""TUM trajectories (round trip, evo, errors) and the summary JSON a replay writes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from h2o_slam.core.geometry import matrix_to_quat, yaw_to_matrix
from h2o_slam.io.bags import ReplayError
from h2o_slam.io.replay_outputs import (
    read_tum,
    seconds_to_ns,
    write_summary,
    write_tum,
    yaw_of_quaternions,
)


def _trajectory(n: int = 50, seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    stamps = 1_700_000_000 * 10**9 + np.cumsum(rng.integers(1, 10**8, n))
    stamps[0] = 1_700_000_000 * 10**9 + 42  # a stamp float seconds cannot hold
    xyz = rng.normal(size=(n, 3)) * [100.0, 100.0, 1.0]
    yaw = rng.uniform(-np.pi, np.pi, n)
    return stamps, xyz, yaw


def test_tum_round_trip_is_bit_exact(tmp_path: Path) -> None:
    stamps, xyz, yaw = _trajectory()
    path = write_tum(tmp_path / "traj.tum", stamps, xyz, yaw_rad=yaw)
    got_stamps, got_xyz, got_q = read_tum(path)
    assert got_stamps.dtype == np.int64 and np.array_equal(got_stamps, stamps)
    assert np.array_equal(got_xyz, xyz)
    assert np.array_equal(got_q, matrix_to_quat(yaw_to_matrix(yaw)))
    np.testing.assert_allclose(yaw_of_quaternions(got_q), yaw, atol=1e-12)
    rotations = yaw_to_matrix(yaw)
    again = write_tum(tmp_path / "again.tum", got_stamps, got_xyz, rotations=rotations)
    assert again.read_text() == path.read_text()


def test_tum_files_load_with_evo(tmp_path: Path) -> None:
    file_interface = pytest.importorskip("evo.tools.file_interface")
    stamps, xyz, yaw = _trajectory()
    path = write_tum(tmp_path / "traj.tum", stamps, xyz[:, :2], yaw_rad=yaw)
    traj = file_interface.read_tum_trajectory_file(str(path))
    assert traj.num_poses == len(stamps)
    np.testing.assert_array_equal(traj.positions_xyz[:, :2], xyz[:, :2])
    np.testing.assert_array_equal(traj.positions_xyz[:, 2], 0.0)
    np.testing.assert_allclose(traj.timestamps, stamps / 1e9, rtol=0, atol=1e-6)
    wxyz = np.roll(matrix_to_quat(yaw_to_matrix(yaw)), 1, axis=1)
    np.testing.assert_array_equal(traj.orientations_quat_wxyz, wxyz)


def test_tum_errors(tmp_path: Path) -> None:
    stamps, xyz, yaw = _trajectory(5)
    with pytest.raises(ReplayError, match="exactly one of yaw_rad or rotations"):
        write_tum(tmp_path / "a.tum", stamps, xyz)
    with pytest.raises(ReplayError, match=r"positions must be \(5, 2 or 3\)"):
        write_tum(tmp_path / "a.tum", stamps, xyz[:4], yaw_rad=yaw)
    bad = xyz.copy()
    bad[2, 0] = np.nan
    with pytest.raises(ReplayError, match="non-finite"):
        write_tum(tmp_path / "a.tum", stamps, bad, yaw_rad=yaw)
    path = tmp_path / "b.tum"
    path.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(ReplayError, match="b.tum: line 3: expected 8 fields, found 7"):
        read_tum(path)
    path.write_text("1.0 0 0 zero 0 0 0 1\n")
    with pytest.raises(ReplayError, match="line 1: could not convert"):
        read_tum(path)


@pytest.mark.parametrize(
    ("text", "ns"),
    [("1700000000.000000042", 1_700_000_000_000_000_042), ("12", 12 * 10**9),
     ("0.5", 500_000_000), ("-0.5", -500_000_000), ("1.5e-3", 1_500_000),
     ("3.1234567891", 3_123_456_789)],
)
def test_seconds_to_ns_is_exact(text: str, ns: int) -> None:
    assert seconds_to_ns(text) == ns


def test_summary_json_takes_numpy_and_nan(tmp_path: Path) -> None:
    path = write_summary(tmp_path / "summary.json", {
        "ate_m": np.float64(0.25), "counts": {"gps": np.int64(3)}, "chi2": np.array([1.0, 2.0]),
        "overrun": float("nan"), "bag": tmp_path, "pair": (1, 2)})
    data = json.loads(path.read_text())
    assert data == {"ate_m": 0.25, "counts": {"gps": 3}, "chi2": [1.0, 2.0], "overrun": None,
                    "bag": str(tmp_path), "pair": [1, 2]}
