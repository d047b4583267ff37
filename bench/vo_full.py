"""Full stereo visual odometers built from OpenCV: the baselines the thesis compares against.

Two of them, both with the same verb (``process(left, right, wheel_delta) -> (3,)``):

:class:`CircularStereoVO` — of the VISO2-S kind (Geiger, Ziegler, Stiller 2011), the reference
full VO of the comparison. Per frame:

1. ORB corners with descriptors in the current left and right images (each image once; the
   previous frame's are kept);
2. circular matching (VISO2's "circle"): previous left → previous right (stereo, on the
   epipolar row) → current right (across time) → current left (stereo) → previous left
   (across time); a match is kept only when the circle closes on the corner it started from.
   The searches across time look within ``match_radius_px`` of where the previous frame's
   rotation predicts the corner, so a sharp turn does not leave them behind;
3. sub-pixel refinement of the three partners of each previous-left corner (KLT started at
   the descriptor match), then bucketing (at most ``per_bucket`` matches per
   ``bucket_px`` cell) so the matches cover the image;
4. RANSAC on 3-D (triangulated in the previous stereo pair) → 2-D (current left)
   correspondences (``cv2.solvePnPRansac``, AP3P minimal sets), then Gauss–Newton on the
   reprojection error in **both** current images on the inliers (VISO2-S's objective),
   inliers re-selected once and refined again;
5. projected to a planar ``base_link`` increment ``(dx_m, dy_m, dyaw_rad)`` through the
   camera mounting.

:class:`FullStereoVO` — the earlier, simpler baseline: Shi–Tomasi corners in the previous
left image, KLT into the previous right image (stereo) and into the current left image
(time, forward–backward checked), ``cv2.solvePnPRansac`` and an LM refinement on the left
image only.

Both fall back to the wheel increment (and count it in ``stats.failed``) when too few
points survive.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from hybrid_vo.camera import CameraIntrinsics, CameraMounting

_LK = {
    "winSize": (21, 21),
    "maxLevel": 3,
    "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
}


def base_from_camera(mounting: CameraMounting) -> np.ndarray:
    """4×4 pose of the left optical frame in ``base_link``."""
    out = np.eye(4)
    out[:3, :3] = mounting.rotation_base_from_optical()
    out[:3, 3] = [mounting.forward_m, mounting.left_m, mounting.height_m]
    return out


def planar_increment(base_from_cam: np.ndarray, rot: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(dx_m, dy_m, dyaw_rad)`` of ``base_link`` from the camera motion ``rot``, ``t``
    (current-from-previous optical frame): the current camera pose in the previous camera
    frame, carried into ``base_link``."""
    cur_from_prev = np.eye(4)
    cur_from_prev[:3, :3] = rot
    cur_from_prev[:3, 3] = t
    base = base_from_cam @ np.linalg.inv(cur_from_prev) @ np.linalg.inv(base_from_cam)
    return np.array([base[0, 3], base[1, 3], math.atan2(base[1, 0], base[0, 0])])


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
        max_features: int = 2000,
        min_inliers: int = 12,
    ) -> None:
        self.k = intrinsics.matrix()
        self.intr = intrinsics
        self.baseline_m = mounting.baseline_m
        self.max_features = max_features
        self.min_inliers = min_inliers
        self._base_from_cam = base_from_camera(mounting)
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
        return planar_increment(self._base_from_cam, rot, tvec[:, 0])


@dataclass(frozen=True)
class CircularVOConfig:
    """Parameters of :class:`CircularStereoVO` (VISO2's defaults where it has one).

    Attributes:
        max_features: ORB corners per image.
        pyramid_levels: ORB's scale levels (VISO2 matches at one scale).
        fast_threshold: ORB's FAST threshold (grey levels).
        stereo_max_dy_px: largest row difference of a stereo match (rectified pair).
        max_disparity_frac: largest disparity as a fraction of the image width.
        min_disparity_px: points with less disparity are not triangulated (their depth is
            mostly noise).
        match_radius_px: search radius across time around the predicted position (VISO2:
            200 px).
        max_hamming: largest descriptor distance of a match (bits of 256).
        bucket_px, per_bucket: bucketing cell size and matches kept per cell (VISO2: 50, 2).
        ransac_iterations, inlier_px: RANSAC trials and reprojection inlier threshold (VISO2:
            200 trials, 2 px).
        gauss_newton_iterations: GN steps on the stereo reprojection error per refinement.
        min_inliers: fewer inliers → fall back to the wheel increment.
    """

    max_features: int = 2000
    fast_threshold: int = 10
    pyramid_levels: int = 2
    stereo_max_dy_px: float = 2.0
    max_disparity_frac: float = 0.25
    min_disparity_px: float = 0.05
    match_radius_px: float = 200.0
    max_hamming: int = 64
    bucket_px: int = 50
    per_bucket: int = 3
    ransac_iterations: int = 200
    inlier_px: float = 2.0
    gauss_newton_iterations: int = 8
    min_inliers: int = 12


@dataclass
class _Features:
    """One image's ORB corners: ``xy`` ``(N, 2)`` float32 pixels and descriptors ``(N, 32)``."""

    xy: np.ndarray
    desc: np.ndarray


@dataclass
class _StereoFrame:
    """A processed stereo pair: both images, their features, and left→right matches."""

    left: np.ndarray
    right: np.ndarray
    fl: _Features
    fr: _Features
    l2r: np.ndarray  # (N_left,) index into fr or -1


_REFINE_LK = {
    "winSize": (11, 11),
    "maxLevel": 1,
    "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01),
    "flags": cv2.OPTFLOW_USE_INITIAL_FLOW,
}


def best_matches(
    desc_a: np.ndarray, desc_b: np.ndarray, allowed: np.ndarray, max_hamming: int
) -> np.ndarray:
    """For each row of ``desc_a`` the index of its nearest ``desc_b`` (Hamming) among the
    ``allowed`` ``(len(a), len(b))`` pairs, or −1 (none allowed, or farther than
    ``max_hamming`` bits)."""
    out = np.full(len(desc_a), -1, dtype=np.int64)
    if len(desc_a) == 0 or len(desc_b) == 0:
        return out
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    matches = matcher.match(desc_a, desc_b, allowed.astype(np.uint8))
    for m in matches:
        if m.distance <= max_hamming and allowed[m.queryIdx, m.trainIdx]:
            out[m.queryIdx] = m.trainIdx
    return out


def windowed_matches(
    xy_a: np.ndarray,
    desc_a: np.ndarray,
    xy_b: np.ndarray,
    desc_b: np.ndarray,
    allow: Callable[[np.ndarray, np.ndarray], np.ndarray],
    axis: int,
    reach_px: float,
    max_hamming: int,
    band_px: float = 16.0,
) -> np.ndarray:
    """:func:`best_matches` with the candidates of each query restricted to ``allow(pa, pb)``
    (positions ``(n, 2)``, ``(m, 2)`` → ``(n, m)`` bool), where ``allow`` never accepts a
    pair more than ``reach_px`` apart along ``axis`` (0: x, 1: y). Queries go in bands of
    ``band_px`` along the axis, each against the candidates within reach, so the work grows
    with the pairs that can match, not with all pairs."""
    out = np.full(len(xy_a), -1, dtype=np.int64)
    if len(xy_a) == 0 or len(xy_b) == 0:
        return out
    order = np.argsort(xy_b[:, axis], kind="stable")
    sorted_b = xy_b[order, axis]
    band = np.floor(xy_a[:, axis] / band_px).astype(np.int64)
    for b in np.unique(band):
        qa = np.flatnonzero(band == b)
        lo = np.searchsorted(sorted_b, b * band_px - reach_px, side="left")
        hi = np.searchsorted(sorted_b, (b + 1) * band_px + reach_px, side="right")
        cb = order[lo:hi]
        if len(cb) == 0:
            continue
        m = best_matches(desc_a[qa], desc_b[cb], allow(xy_a[qa], xy_b[cb]), max_hamming)
        hit = m >= 0
        out[qa[hit]] = cb[m[hit]]
    return out


def circular_matches(
    p_l2r: np.ndarray, pr_to_cr: np.ndarray, cr_to_cl: np.ndarray, cl_to_pl: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Close VISO2's circle: indices ``(pl, pr, cr, cl)`` of the previous-left corners whose
    chain previous left → previous right → current right → current left → previous left
    returns to the corner it started from (each map is an index array, −1 for no match)."""
    pl = np.flatnonzero(p_l2r >= 0)
    pr = p_l2r[pl]
    cr = pr_to_cr[pr]
    ok = cr >= 0
    pl, pr, cr = pl[ok], pr[ok], cr[ok]
    cl = cr_to_cl[cr]
    ok = cl >= 0
    pl, pr, cr, cl = pl[ok], pr[ok], cr[ok], cl[ok]
    ok = cl_to_pl[cl] == pl
    return pl[ok], pr[ok], cr[ok], cl[ok]


def bucket(xy: np.ndarray, cell_px: int, per_cell: int) -> np.ndarray:
    """Indices of at most ``per_cell`` points ``(N, 2)`` per ``cell_px`` square (first come)."""
    if len(xy) == 0:
        return np.zeros(0, dtype=np.int64)
    cells = np.floor(xy / cell_px).astype(np.int64)
    key = cells[:, 0] * 100_003 + cells[:, 1]
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    start = np.r_[0, np.flatnonzero(np.diff(sorted_key)) + 1]
    rank = np.arange(len(key)) - np.repeat(start, np.diff(np.r_[start, len(key)]))
    return np.sort(order[rank < per_cell])


def stereo_residuals(
    rot: np.ndarray, t: np.ndarray, pts: np.ndarray, obs: np.ndarray, k: np.ndarray,
    baseline_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Reprojection residuals ``(N, 4)`` (left u, v; right u, v) of the previous-frame points
    ``pts`` ``(N, 3)`` moved by ``rot``, ``t`` (current-from-previous camera) against ``obs``
    ``(N, 4)`` (left u, v, right u, v), and their Jacobians ``(N, 4, 6)`` with respect to a
    left-multiplied twist ``(ω, v)``."""
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    p = pts @ rot.T + t
    x, y, z = p[:, 0], p[:, 1], np.maximum(p[:, 2], 1e-6)
    pred = np.stack(
        [fx * x / z + cx, fy * y / z + cy, fx * (x - baseline_m) / z + cx, fy * y / z + cy], 1
    )
    res = pred - obs
    # d(projection)/dP, rows: left u, left v, right u, right v.
    dproj = np.zeros((len(p), 4, 3))
    dproj[:, 0, 0] = fx / z
    dproj[:, 0, 2] = -fx * x / z**2
    dproj[:, 1, 1] = fy / z
    dproj[:, 1, 2] = -fy * y / z**2
    dproj[:, 2, 0] = fx / z
    dproj[:, 2, 2] = -fx * (x - baseline_m) / z**2
    dproj[:, 3] = dproj[:, 1]
    # dP/d(ω, v) = [-[P]×, I].
    dp = np.zeros((len(p), 3, 6))
    dp[:, 0, 1], dp[:, 0, 2] = p[:, 2], -p[:, 1]
    dp[:, 1, 0], dp[:, 1, 2] = -p[:, 2], p[:, 0]
    dp[:, 2, 0], dp[:, 2, 1] = p[:, 1], -p[:, 0]
    dp[:, :, 3:] = np.eye(3)
    return res, dproj @ dp


def gauss_newton(
    rot: np.ndarray, t: np.ndarray, pts: np.ndarray, obs: np.ndarray, k: np.ndarray,
    baseline_m: float, iterations: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Minimise the stereo reprojection error over the motion ``(rot, t)`` by Gauss–Newton."""
    for _ in range(iterations):
        res, jac = stereo_residuals(rot, t, pts, obs, k, baseline_m)
        j = jac.reshape(-1, 6)
        try:
            step = np.linalg.solve(j.T @ j + 1e-9 * np.eye(6), -j.T @ res.reshape(-1))
        except np.linalg.LinAlgError:
            break
        d_rot, _ = cv2.Rodrigues(step[:3])
        rot, t = d_rot @ rot, d_rot @ t + step[3:]
        if float(np.max(np.abs(step))) < 1e-9:
            break
    return rot, t


class CircularStereoVO:
    """Stereo VO of the VISO2-S kind (see the module docstring) with planar output."""

    def __init__(
        self,
        intrinsics: CameraIntrinsics,
        mounting: CameraMounting,
        config: CircularVOConfig | None = None,
    ) -> None:
        self.config = config if config is not None else CircularVOConfig()
        self.k = intrinsics.matrix()
        self.intr = intrinsics
        self.baseline_m = mounting.baseline_m
        self._base_from_cam = base_from_camera(mounting)
        self._orb = cv2.ORB_create(
            nfeatures=4 * self.config.max_features, fastThreshold=self.config.fast_threshold,
            nlevels=self.config.pyramid_levels,
        )
        self._prev: _StereoFrame | None = None
        # Current-from-previous camera rotation of the last frame: predicts the next flow.
        self._last_rot = np.eye(3)
        self.stats = FullVOStats()
        self.last_inliers = 0

    def process(self, left: np.ndarray, right: np.ndarray, wheel_delta: np.ndarray) -> np.ndarray:
        """Planar increment ``(3,)`` of ``base_link`` since the previous frame."""
        self.stats.frames += 1
        cur = self._stereo(left, right)
        prev, self._prev = self._prev, cur
        if prev is None:
            return np.asarray(wheel_delta, float).copy()
        motion = self._motion(prev, cur)
        if motion is None:
            self.stats.failed += 1
            self._last_rot = np.eye(3)
            return np.asarray(wheel_delta, float).copy()
        rot, t = motion
        self._last_rot = rot
        return planar_increment(self._base_from_cam, rot, t)

    def _features(self, image: np.ndarray) -> _Features:
        # VISO2 spreads its corners with a non-maximum suppression grid; ORB's strongest
        # corners otherwise crowd onto the most textured object in view. Strongest first,
        # at most an equal share per bucket cell.
        cfg = self.config
        kps = self._orb.detect(image, None)
        if kps:
            xy = np.array([kp.pt for kp in kps], dtype=np.float32)
            order = np.argsort([-kp.response for kp in kps], kind="stable")
            cells = (image.shape[0] // cfg.bucket_px + 1) * (image.shape[1] // cfg.bucket_px + 1)
            share = max(1, cfg.max_features // cells)
            keep = order[bucket(xy[order], cfg.bucket_px, share)]
            kps = [kps[i] for i in keep]  # strongest first (bucket keeps the order)
        kps, desc = self._orb.compute(image, kps)
        if desc is None or not kps:
            return _Features(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8))
        return _Features(np.array([kp.pt for kp in kps], dtype=np.float32), desc)

    def _stereo_allow(self, pl: np.ndarray, pr: np.ndarray) -> np.ndarray:
        """Pairs (left ``(n, 2)``, right ``(m, 2)``) on the same row with a disparity in range."""
        cfg = self.config
        disp = pl[:, None, 0] - pr[None, :, 0]
        return (
            (np.abs(pl[:, None, 1] - pr[None, :, 1]) <= cfg.stereo_max_dy_px)
            & (disp >= 0.0) & (disp <= cfg.max_disparity_frac * self.intr.width_px)
        )

    def _stereo(self, left: np.ndarray, right: np.ndarray) -> _StereoFrame:
        fl, fr = self._features(left), self._features(right)
        cfg = self.config
        l2r = windowed_matches(fl.xy, fl.desc, fr.xy, fr.desc, self._stereo_allow, 1,
                               cfg.stereo_max_dy_px, cfg.max_hamming)
        return _StereoFrame(left, right, fl, fr, l2r)

    def _predicted(self, xy: np.ndarray) -> np.ndarray:
        """Where the last frame's rotation (a homography K R K⁻¹) moves pixels ``(N, 2)``."""
        h = self.k @ self._last_rot @ np.linalg.inv(self.k)
        ph = np.c_[xy, np.ones(len(xy))] @ h.T
        return np.asarray(ph[:, :2] / ph[:, 2:3], dtype=np.float32)

    def _across_time(self, a: _Features, query: np.ndarray, b: _Features, forward: bool
                     ) -> np.ndarray:
        """Matches of the corners ``query`` of ``a`` into ``b`` (−1 elsewhere) within the
        search radius of the predicted position (``forward``: ``a`` is the previous image)."""
        radius = self.config.match_radius_px
        pa, pb = (self._predicted(a.xy[query]), b.xy) if forward else (
            a.xy[query], self._predicted(b.xy))

        def near(x: np.ndarray, y: np.ndarray) -> np.ndarray:
            dx = x[:, None, 0] - y[None, :, 0]
            dy = x[:, None, 1] - y[None, :, 1]
            return np.asarray(dx * dx + dy * dy <= radius**2)

        out = np.full(len(a.xy), -1, dtype=np.int64)
        out[query] = windowed_matches(pa, a.desc[query], pb, b.desc, near, 0, radius,
                                      self.config.max_hamming, band_px=radius / 4)
        return out

    def _motion(
        self, prev: _StereoFrame, cur: _StereoFrame
    ) -> tuple[np.ndarray, np.ndarray] | None:
        cfg = self.config
        # Only the corners on a circle that can still close are matched onward.
        pr_to_cr = self._across_time(prev.fr, np.unique(prev.l2r[prev.l2r >= 0]), cur.fr,
                                     forward=True)
        reached_cr = np.unique(pr_to_cr[pr_to_cr >= 0])
        cr_to_cl = np.full(len(cur.fr.xy), -1, dtype=np.int64)
        cr_to_cl[reached_cr] = windowed_matches(
            cur.fr.xy[reached_cr], cur.fr.desc[reached_cr], cur.fl.xy, cur.fl.desc,
            lambda r, left: self._stereo_allow(left, r).T, 1, cfg.stereo_max_dy_px,
            cfg.max_hamming)
        cl_to_pl = self._across_time(cur.fl, np.unique(cr_to_cl[cr_to_cl >= 0]), prev.fl,
                                     forward=False)
        pl, pr, cr, cl = circular_matches(prev.l2r, pr_to_cr, cr_to_cl, cl_to_pl)
        if len(pl) < cfg.min_inliers:
            return None
        # Sub-pixel: refine the three partners of each previous-left corner by KLT.
        anchor = prev.fl.xy[pl].reshape(-1, 1, 2)
        obs = []
        good = np.ones(len(pl), dtype=bool)
        for image, start in ((prev.right, prev.fr.xy[pr]), (cur.left, cur.fl.xy[cl]),
                             (cur.right, cur.fr.xy[cr])):
            guess = start.reshape(-1, 1, 2).copy()
            found, st, _ = cv2.calcOpticalFlowPyrLK(prev.left, image, anchor, guess, **_REFINE_LK)
            good &= (st[:, 0] == 1) & (np.linalg.norm(found[:, 0] - start, axis=1) < 2.0)
            obs.append(found[:, 0].astype(np.float64))
        a = anchor[:, 0].astype(np.float64)
        rp, lc, rc = obs
        disp_p = a[:, 0] - rp[:, 0]
        good &= (np.abs(a[:, 1] - rp[:, 1]) < 1.0) & (disp_p > cfg.min_disparity_px)
        good &= (np.abs(lc[:, 1] - rc[:, 1]) < 1.0) & (lc[:, 0] - rc[:, 0] > 0.0)
        keep = np.flatnonzero(good)
        keep = keep[bucket(a[keep], cfg.bucket_px, cfg.per_bucket)]
        if len(keep) < cfg.min_inliers:
            return None
        intr = self.intr
        z = intr.fx_px * self.baseline_m / disp_p[keep]
        pts = np.stack([(a[keep, 0] - intr.cx_px) * z / intr.fx_px,
                        (a[keep, 1] - intr.cy_px) * z / intr.fy_px, z], axis=1)
        obs4 = np.c_[lc[keep], rc[keep]]
        found, rvec, tvec, inliers = cv2.solvePnPRansac(
            pts, lc[keep], self.k, None, iterationsCount=cfg.ransac_iterations,
            reprojectionError=cfg.inlier_px, confidence=0.999, flags=cv2.SOLVEPNP_AP3P,
        )
        if not found or inliers is None or len(inliers) < cfg.min_inliers:
            return None
        rot, _ = cv2.Rodrigues(rvec)
        t = tvec[:, 0].astype(np.float64)
        idx = inliers[:, 0]
        for _ in range(2):
            rot, t = gauss_newton(rot, t, pts[idx], obs4[idx], self.k, self.baseline_m,
                                  cfg.gauss_newton_iterations)
            res, _ = stereo_residuals(rot, t, pts, obs4, self.k, self.baseline_m)
            idx = np.flatnonzero(np.all(np.abs(res) < cfg.inlier_px, axis=1))
            if len(idx) < cfg.min_inliers:
                return None
        rot, t = gauss_newton(rot, t, pts[idx], obs4[idx], self.k, self.baseline_m,
                              cfg.gauss_newton_iterations)
        self.last_inliers = len(idx)
        return rot, t
