"""Hybrid VO yaw vs full stereo VO vs ground truth on a real KITTI stereo sequence.

The folder holds ``calib.txt`` (KITTI ``P0``/``P1`` rows: 3×4 projection matrices of the
rectified left and right grey cameras), ``image_l/NNNNNN.png``, ``image_r/NNNNNN.png`` and
``poses.txt`` (one 3×4 pose of the left camera in the first left-camera frame per line,
frames 0, 1, …). KITTI has no wheel odometry, so the "wheels" are simulated from the ground
truth as on the synthetic drives: the true planar travel, and the true yaw increment plus a
random walk of ``yaw_sigma_rad_per_sqrt_m`` (``WheelSlipConfig``'s default) and, with
``hallucinated_turn_rad``, a turn the car did not make spread over ten frames in the middle.
Both odometers see the same frames in the same run; CPU time per frame is
``time.process_time``. The camera is taken as ``base_link`` (KITTI's cam0 sits 1.65 m above
the road, level).

Usage::

    .venv/bin/python bench/vo_kitti.py /work/shared/data/kitti_stereo/sequence_1
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from vo_full import FullStereoVO  # noqa: E402

from hybrid_vo.camera import CameraIntrinsics, CameraMounting  # noqa: E402
from hybrid_vo.frames import StereoFrame  # noqa: E402
from hybrid_vo.odometer import HybridOdometer, OdometerConfig  # noqa: E402
from hybrid_vo.world import integrate, relative_pose, wrap_angle  # noqa: E402

#: KITTI's left grey camera above the road (their set-up description).
KITTI_CAMERA_HEIGHT_M = 1.65
#: d of (2.3) comes from the top speed: the car drives at ~12 m/s, not the thesis' 1.3.
KITTI_CONFIG = OdometerConfig(max_speed_m_s=15.0)


@dataclass(frozen=True)
class KittiResult:
    """Accuracy and cost of the three odometers on one sequence.

    Attributes:
        frames: frames with a ground-truth pose.
        length_m: path length of the ground truth.
        yaw_rmse_rad: per-frame yaw-increment error RMSE for ``wheel``, ``hybrid``, ``full``.
        final_yaw_err_rad: heading error at the last frame, same keys.
        final_pos_err_m: position error at the last frame, same keys.
        hybrid_ms, full_ms: mean CPU ms per frame.
        deferred: fraction of frames the hybrid odometer left to the wheels.
    """

    frames: int
    length_m: float
    yaw_rmse_rad: dict[str, float]
    final_yaw_err_rad: dict[str, float]
    final_pos_err_m: dict[str, float]
    hybrid_ms: float
    full_ms: float
    deferred: float


def read_calib(path: Path) -> tuple[CameraIntrinsics, float, tuple[int, int]]:
    """Intrinsics and baseline (m) from ``calib.txt``; the image size from the first image."""
    rows = [np.array(line.split()[-12:], dtype=float).reshape(3, 4)
            for line in path.read_text().splitlines() if line.strip()]
    p0, p1 = rows[0], rows[1]
    first = sorted((path.parent / "image_l").glob("*.png"))[0]
    img = cv2.imread(str(first), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise FileNotFoundError(f"cannot read {first}")
    h, w = img.shape
    intr = CameraIntrinsics(w, h, p0[0, 0], p0[1, 1], p0[0, 2], p0[1, 2])
    baseline = -(p1[0, 3] - p0[0, 3]) / p1[0, 0]
    return intr, float(baseline), (w, h)


def planar_poses(path: Path) -> np.ndarray:
    """``(N, 3)`` planar ``base_link`` poses from KITTI camera poses (x right, y down, z fwd)."""
    mats = np.loadtxt(path).reshape(-1, 3, 4)
    # base x = camera z, base y = −camera x; yaw of the camera's forward axis.
    return np.stack(
        [mats[:, 2, 3], -mats[:, 0, 3], np.arctan2(-mats[:, 0, 2], mats[:, 2, 2])], axis=-1
    )


def simulated_wheels(
    truth: np.ndarray, seed: int, yaw_sigma_rad_per_sqrt_m: float, hallucinated_turn_rad: float
) -> np.ndarray:
    """``(N, 3)`` wheel increments (row 0 zero) from the true path, as ``world._wheel`` does."""
    rng = np.random.default_rng(seed)
    true = relative_pose(truth[:-1], truth[1:])
    ds = np.hypot(true[:, 0], true[:, 1])
    yaw = true[:, 2] + yaw_sigma_rad_per_sqrt_m * np.sqrt(ds) * rng.standard_normal(len(ds))
    if hallucinated_turn_rad:
        mid = len(yaw) // 2
        yaw[mid : mid + 10] += hallucinated_turn_rad / len(yaw[mid : mid + 10])
    wheel = np.stack([ds * np.cos(yaw / 2), ds * np.sin(yaw / 2), yaw], axis=-1)
    return np.vstack([np.zeros(3), wheel])


def run_kitti(
    folder: Path,
    seed: int = 0,
    yaw_sigma_rad_per_sqrt_m: float = 0.004,
    hallucinated_turn_rad: float = 0.0,
    config: OdometerConfig = KITTI_CONFIG,
) -> KittiResult:
    """Run wheel-only, hybrid (with ``config``) and full VO over the sequence in ``folder``."""
    intr, baseline, _ = read_calib(folder / "calib.txt")
    truth = planar_poses(folder / "poses.txt")
    lefts = sorted((folder / "image_l").glob("*.png"))[: len(truth)]
    rights = sorted((folder / "image_r").glob("*.png"))[: len(truth)]
    truth = truth[: len(lefts)]
    wheel = simulated_wheels(truth, seed, yaw_sigma_rad_per_sqrt_m, hallucinated_turn_rad)
    mount = CameraMounting(height_m=KITTI_CAMERA_HEIGHT_M, baseline_m=baseline)
    hybrid = HybridOdometer(intr, mount, config)
    full = FullStereoVO(intr, mount)
    h_inc, f_inc, h_cpu, f_cpu = [], [], [], []
    for i, (lp, rp) in enumerate(zip(lefts, rights, strict=True)):
        left = cv2.imread(str(lp), cv2.IMREAD_GRAYSCALE)
        right = cv2.imread(str(rp), cv2.IMREAD_GRAYSCALE)
        t0 = time.process_time()
        upd = hybrid.process(StereoFrame(left, right, i), wheel[i])
        t1 = time.process_time()
        f = full.process(left, right, wheel[i])
        t2 = time.process_time()
        h_inc.append(upd.delta)
        f_inc.append(f)
        if i > 0:
            h_cpu.append(t1 - t0)
            f_cpu.append(t2 - t1)
    true_inc = relative_pose(truth[:-1], truth[1:])
    incs = {"wheel": wheel[1:], "hybrid": np.array(h_inc)[1:], "full": np.array(f_inc)[1:]}
    poses = {k: integrate(truth[0], v) for k, v in incs.items()}
    return KittiResult(
        frames=len(truth),
        length_m=float(np.sum(np.hypot(true_inc[:, 0], true_inc[:, 1]))),
        yaw_rmse_rad={k: float(np.sqrt(np.mean(wrap_angle(v[:, 2] - true_inc[:, 2]) ** 2)))
                      for k, v in incs.items()},
        final_yaw_err_rad={k: float(abs(wrap_angle(v[-1, 2] - truth[-1, 2])))
                           for k, v in poses.items()},
        final_pos_err_m={k: float(math.hypot(*(v[-1, :2] - truth[-1, :2])))
                         for k, v in poses.items()},
        hybrid_ms=1e3 * float(np.mean(h_cpu)),
        full_ms=1e3 * float(np.mean(f_cpu)),
        deferred=hybrid.stats.deferred_fraction,
    )


def table(rows: list[tuple[str, KittiResult]]) -> str:
    """Markdown table, one row per (label, result)."""
    out = [
        "| KITTI run | frames | length m | hybrid ms | full VO ms | hybrid/full cost | "
        "deferred to wheels | yaw-increment RMSE rad wheel / hybrid / full | "
        "final heading err rad wheel / hybrid / full | final pos err m wheel / hybrid / full |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for label, r in rows:
        def trio(d: dict[str, float]) -> str:
            return " / ".join(f"{d[k]:.3g}" for k in ("wheel", "hybrid", "full"))

        out.append(
            f"| {label} | {r.frames} | {r.length_m:.1f} | {r.hybrid_ms:.2f} | {r.full_ms:.1f} | "
            f"{100 * r.hybrid_ms / r.full_ms:.1f}% | {100 * r.deferred:.1f}% | "
            f"{trio(r.yaw_rmse_rad)} | {trio(r.final_yaw_err_rad)} | {trio(r.final_pos_err_m)} |"
        )
    return "\n".join(out)


def kitti_rows(folder: Path, seed: int) -> list[tuple[str, KittiResult]]:
    """The runs bench/vo.py reports: mild wheels (with and without the parallax correction),
    and wheels with a 0.3 rad false turn."""
    no_corr = replace(KITTI_CONFIG, parallax_correction=False)
    return [
        ("wheels: truth + yaw noise", run_kitti(folder, seed)),
        ("same, parallax_correction=False", run_kitti(folder, seed, config=no_corr)),
        ("wheels: + 0.3 rad false turn", run_kitti(folder, seed, hallucinated_turn_rad=0.3)),
    ]


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point: prints the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    print(table(kitti_rows(args.folder, args.seed)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
