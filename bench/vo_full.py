"""A full stereo visual odometer built from OpenCV: the baseline the thesis compares against.

Per frame (typical full-resolution pipeline, e.g. 640×480):

1. Shi–Tomasi corners (``cv2.goodFeaturesToTrack``) in the previous left image;
2. stereo matching of those corners into the previous right image (pyramidal KLT,
   constrained to the epipolar row of the rectified pair) → 3-D points in the previous
   left-camera frame;
3. temporal tracking of the corners into the current left image (pyramidal KLT with a
   forward–backward check);
4. ``cv2.solvePnPRansac`` (3-D previous → 2-D current) → 6-DOF camera motion, refined on
   the inliers with Levenberg–Marquardt;
5. projected to a planar ``base_link`` increment ``(dx_m, dy_m, dyaw_rad)`` through the camera
   mounting.

Falls back to the wheel increment (and counts it) when too few points survive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from hybrid_vo.camera import CameraIntrinsics, CameraMounting

_LK = {
    "winSize": (21, 21),
    "maxLevel": 3,
    "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
}


@dataclass
class FullVOStats:
    """Counters: frames processed and frames that fell back to the wheel increment."""

    frames: int = 0
    failed: int = 0


class FullStereoVO:
    """Feature-based stereo VO (KLT + stereo + PnP RANSAC) with planar output."""

    def __init__(
        self,
        intrinsics: CameraIntrinsics,
        mounting: CameraMounting,
        max_features: int = 1000,
        min_inliers: int = 12,
    ) -> None:
        self.k = intrinsics.matrix()
        self.intr = intrinsics
        self.baseline_m = mounting.baseline_m
        self.max_features = max_features
        self.min_inliers = min_inliers
        r_bo = mounting.rotation_base_from_optical()
        t_bo = np.array([mounting.forward_m, mounting.left_m, mounting.height_m])
        self._base_from_cam = np.eye(4)
        self._base_from_cam[:3, :3] = r_bo
        self._base_from_cam[:3, 3] = t_bo
        self._cam_from_base = np.linalg.inv(self._base_from_cam)
        self._prev: tuple[np.ndarray, np.ndarray] | None = None
        self.stats = FullVOStats()

    def process(self, left: np.ndarray, right: np.ndarray, wheel_delta: np.ndarray) -> np.ndarray:
        """Planar increment ``(3,)`` of ``base_link`` since the previous frame."""
        self.stats.frames += 1
        prev, self._prev = self._prev, (left, right)
        if prev is None:
            return np.asarray(wheel_delta, float).copy()
        result = self._motion(prev[0], prev[1], left)
        if result is None:
            self.stats.failed += 1
            return np.asarray(wheel_delta, float).copy()
        return result

    def _motion(self, pl: np.ndarray, pr: np.ndarray, cl: np.ndarray) -> np.ndarray | None:
        pts = cv2.goodFeaturesToTrack(pl, self.max_features, 0.01, 7, blockSize=5)
        if pts is None or len(pts) < self.min_inliers:
            return None
        # Stereo: KLT into the right image, starting a few pixels left (far points).
        guess = pts.copy()
        guess[:, 0, 0] -= 2.0
        pr_pts, st, _ = cv2.calcOpticalFlowPyrLK(
            pl, pr, pts, guess, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **_LK
        )
        disp = pts[:, 0, 0] - pr_pts[:, 0, 0]
        ok = (st[:, 0] == 1) & (np.abs(pts[:, 0, 1] - pr_pts[:, 0, 1]) < 1.0) & (disp > 0.5)
        # Temporal: KLT into the current left image with a forward-backward check.
        cur, st2, _ = cv2.calcOpticalFlowPyrLK(pl, cl, pts, None, **_LK)
        back, st3, _ = cv2.calcOpticalFlowPyrLK(cl, pl, cur, None, **_LK)
        fb = np.linalg.norm((back - pts)[:, 0], axis=1)
        ok &= (st2[:, 0] == 1) & (st3[:, 0] == 1) & (fb < 0.5)
        if int(ok.sum()) < self.min_inliers:
            return None
        intr = self.intr
        z = intr.fx_px * self.baseline_m / disp[ok]
        u, v = pts[ok, 0, 0], pts[ok, 0, 1]
        obj = np.stack(
            [(u - intr.cx_px) * z / intr.fx_px, (v - intr.cy_px) * z / intr.fy_px, z], axis=1
        )
        img = cur[ok, 0, :].astype(np.float64)
        found, rvec, tvec, inliers = cv2.solvePnPRansac(
            obj, img, self.k, None, iterationsCount=100, reprojectionError=1.0,
            confidence=0.999, flags=cv2.SOLVEPNP_ITERATIVE,
        )
        if not found or inliers is None or len(inliers) < self.min_inliers:
            return None
        idx = inliers[:, 0]
        rvec, tvec = cv2.solvePnPRefineLM(obj[idx], img[idx], self.k, None, rvec, tvec)
        rot, _ = cv2.Rodrigues(rvec)
        cur_from_prev = np.eye(4)
        cur_from_prev[:3, :3] = rot
        cur_from_prev[:3, 3] = tvec[:, 0]
        # Pose of the current camera in the previous camera frame, then in base_link.
        prev_from_cur = np.linalg.inv(cur_from_prev)
        base = self._base_from_cam @ prev_from_cur @ self._cam_from_base
        return np.array([base[0, 3], base[1, 3], math.atan2(base[1, 0], base[0, 0])])
