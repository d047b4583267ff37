"""The hybrid wheel/visual odometer (thesis ch. 2): one verb, :meth:`HybridOdometer.process`.

Per stereo frame and wheel increment since the previous frame:

1. downsample to the working resolution (thesis: 160×120) and remap the left image's
   horizon band to the spherical image through the precomputed table (2.1)–(2.2);
2. sample ``num_patches`` patches at Harris corners in ``−θ_max < θ < θ_max`` of the
   *previous* spherical image — or, when wheel odometry says the turn would carry that region
   off the image, in the region that will become frontal (§2.3.3);
3. drop patches nearer than ``r_min`` of (2.3), measured by per-patch stereo;
4. search each patch by NCC in a window spanning its previous position and the one predicted
   by the wheel yaw, inflated by half a patch;
5. cross-validate the patches' yaw estimates by vote (§2.3.4);
6. replace the wheel yaw by the visual one with the midpoint rule (2.4); yaw σ from the
   curvature of the NCC peaks (§2.3.5).

When too few patches survive or no consensus forms, the frame defers to wheel odometry and
says why (:class:`FallbackReason`). Increments are ``(dx_m, dy_m, dyaw_rad)`` of the new
``base_link`` pose in the previous one (``T_prev⁻¹ T_new``); wheel increments use the same
convention (what consecutive ``nav_msgs/Odometry`` poses give).
"""

from __future__ import annotations

import enum
import math
import statistics
import time
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from h2o_slam.core.parameters import parameter
from hybrid_vo import patches as pt
from hybrid_vo.camera import CameraIntrinsics, CameraMounting, SphericalMap
from hybrid_vo.errors import ConfigError, FrameError
from hybrid_vo.frames import StereoFrame

FloatArray = NDArray[np.float64]
Float32Array = NDArray[np.float32]


class FallbackReason(enum.Enum):
    """Why a frame's increment came from wheel odometry alone (``NONE``: it did not)."""

    NONE = "none"
    FIRST_FRAME = "first_frame"  # nothing to compare with yet
    BLANK_VIEW = "blank_view"  # too few corners in the sampling region (sky, fog, lens cap)
    NEAR_FEATURES = "near_features"  # too few patches beyond r_min (2.3): the view is blocked
    POOR_MATCH = "poor_match"  # too few patches found again with enough correlation
    NO_CONSENSUS = "no_consensus"  # the vote (§2.3.4) left no inlier


@dataclass(frozen=True)
class OdometerConfig:
    """Parameters of the hybrid odometer; defaults follow the thesis (§2.3–2.4). The node
    declares each documented field as ``odometer.<name>`` (``metadata``:
    :mod:`ros_node_base.params`).

    Attributes:
        work_width_px: images are downsampled to this width (thesis: 160); the height keeps
            the camera's aspect ratio (120 for a 4:3 camera).
        num_patches: patches sampled per frame (thesis: 6).
        patch_width_px, patch_height_px: patch size in spherical pixels (thesis: 13×3).
        band_half_height_rad: the spherical image covers this much pitch above and below
            the horizon.
        theta_max_rad: half-width of the sampling region about the frontal direction;
            0 derives it from the mounting as the thesis does (the bearing of the image
            side nearest to the frontal direction, less half a patch), capped at
            ``theta_max_cap_rad``.
        max_speed_m_s, frame_rate_hz: give ``d = max_speed / frame_rate``, the largest travel
            between frames in (2.3) (thesis: 1.3 m/s at 10 Hz → 0.13 m).
        candidate_factor: up to ``candidate_factor · num_patches`` corners are range-tested,
            strongest first, until ``num_patches`` pass (2.3).
        min_patches: fewer surviving patches → defer to wheel odometry.
        min_ncc: a patch match below this normalized cross-correlation is discarded.
        harris_min_response: corner threshold relative to the band's contrast; a blank view
            has none above it.
        stereo_max_disparity_px, stereo_min_ncc, stereo_half_width_px,
        stereo_half_height_px: per-patch stereo range (working resolution).
        fallback_yaw_sigma_rad: yaw σ reported on frames that defer to the wheels.
        yaw_sigma_floor_rad: lower bound of the reported yaw σ (never a zero covariance).
        sigma_merge: ``"thesis"`` (as printed) or ``"inverse_variance"``; see
            :func:`hybrid_vo.patches.merge_sigmas`.
        parallax_correction: subtract from each patch's yaw the parallax that the wheel
            travel and the patch's stereo range predict (:func:`hybrid_vo.patches.parallax_rad`);
            False keeps the thesis' assumption that parallax below ``θ_p/2`` is invisible.
        balance_sides: take patches alternately from both sides of the direction of travel
            and give both sides equal weight, so that the parallax of features too far to
            range cancels (:func:`hybrid_vo.patches.alternate_sides`).
        parallax_min_disparity_px: patches with less stereo disparity than this are taken
            as infinitely far by the parallax correction (for cameras whose sub-pixel
            disparity is too noisy to be worth using).
        stereo_at_input_resolution: range patches on the stereo pair as it arrives rather
            than on the downsampled one (``stereo_*`` sizes are in working pixels and
            scale with it).
        match_blur_px: σ (spherical pixels) of a Gaussian blur of the spherical image before
            corners and NCC; widens the NCC peak so the sub-pixel parabola is not pulled
            toward whole pixels. 0 matches on the image as remapped (the thesis).
        symmetric_subpixel: average the forward match with a match back from the current
            frame (:func:`hybrid_vo.patches.track_patch`); False uses the forward parabola.
    """

    work_width_px: int = parameter(
        160, "Images are downsampled to this width (the height keeps the aspect ratio). "
        "Thesis: 160 (160x120 for a 4:3 camera).", bounds=(32, 4096))
    num_patches: int = parameter(6, "Patches tracked per frame. Thesis: 6.", bounds=(1, 64))
    patch_width_px: int = parameter(
        13, "Patch width in spherical pixels, odd. Thesis: 13.", bounds=(3, 63))
    patch_height_px: int = parameter(
        3, "Patch height in spherical pixels, odd. Thesis: 3.", bounds=(3, 63))
    band_half_height_rad: float = parameter(
        0.1, "The horizon band covers this pitch above and below the horizon, rad.",
        bounds=(0.01, 0.8))
    theta_max_rad: float = parameter(
        0.0, "Half-width of the patch sampling region about straight ahead, rad; 0 derives "
        "it from the mounting as the thesis does (capped at 0.14).", bounds=(0.0, 1.5))
    theta_max_cap_rad: float = 0.14
    max_speed_m_s: float = parameter(
        1.3, "Largest robot speed, m/s; with frame_rate_hz it gives the travel between "
        "frames of the range test (2.3), which drops features nearer than r_min.",
        bounds=(0.01, 50.0))
    frame_rate_hz: float = parameter(10.0, "Camera frame rate, Hz.", bounds=(0.1, 200.0))
    candidate_factor: int = 3
    min_patches: int = parameter(
        3, "Fewer usable patches than this and the frame uses wheel odometry (at most "
        "num_patches).", bounds=(1, 64))
    min_ncc: float = parameter(
        0.75, "A patch match below this normalized cross-correlation is discarded.",
        bounds=(-0.99, 0.99))
    harris_min_response: float = 1e-5
    stereo_max_disparity_px: int = 40
    stereo_min_ncc: float = 0.6
    stereo_half_width_px: int = 4
    stereo_half_height_px: int = 2
    fallback_yaw_sigma_rad: float = parameter(
        0.02, "Yaw sigma given to a frame that uses wheel odometry, rad.", bounds=(1e-6, 1.0))
    yaw_sigma_floor_rad: float = 1e-4
    sigma_merge: Literal["thesis", "inverse_variance"] = parameter(
        "thesis", "How the patches' yaw sigmas combine: thesis (as printed) or inverse_variance.")
    parallax_correction: bool = parameter(
        True, "Beyond the thesis: remove from each patch the parallax predicted from the "
        "wheel travel and its stereo range.")
    balance_sides: bool = parameter(
        True, "Beyond the thesis: take patches from both sides of the direction of travel, "
        "equally weighted.")
    parallax_min_disparity_px: float = parameter(
        0.0, "Patches with less stereo disparity are taken as infinitely far, px.",
        bounds=(0.0, 100.0))
    symmetric_subpixel: bool = parameter(
        True, "Beyond the thesis: average the forward match with a match back from the "
        "current frame.")
    stereo_at_input_resolution: bool = parameter(
        True, "Beyond the thesis: range patches on the stereo pair as it arrives, not the "
        "downsampled one.")
    match_blur_px: float = parameter(
        1.0, "Beyond the thesis: Gaussian blur (sigma, spherical px) before corners and "
        "NCC; 0 disables (all four options off and this 0 is the thesis algorithm).",
        bounds=(0.0, 10.0))

    def __post_init__(self) -> None:
        def positive(name: str) -> None:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be finite and > 0, got {value!r}")

        for name in (
            "work_width_px",
            "num_patches",
            "band_half_height_rad",
            "theta_max_cap_rad",
            "max_speed_m_s",
            "frame_rate_hz",
            "min_patches",
            "candidate_factor",
            "stereo_max_disparity_px",
            "stereo_half_width_px",
            "stereo_half_height_px",
            "fallback_yaw_sigma_rad",
            "yaw_sigma_floor_rad",
        ):
            positive(name)
        if not (math.isfinite(self.theta_max_rad) and self.theta_max_rad >= 0.0):
            raise ConfigError(f"theta_max_rad must be finite and >= 0, got {self.theta_max_rad!r}")
        for name in ("patch_width_px", "patch_height_px"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 3 or value % 2 == 0:
                raise ConfigError(f"{name} must be an odd integer >= 3, got {value!r}")
        if self.work_width_px < 32:
            raise ConfigError(f"work_width_px must be >= 32, got {self.work_width_px!r}")
        if self.min_patches > self.num_patches:
            raise ConfigError(
                f"min_patches ({self.min_patches}) cannot exceed num_patches ({self.num_patches})"
            )
        for name in ("min_ncc", "stereo_min_ncc"):
            value = getattr(self, name)
            if not -1.0 < value < 1.0:
                raise ConfigError(f"{name} must lie in (-1, 1), got {value!r}")
        if not (math.isfinite(self.match_blur_px) and self.match_blur_px >= 0):
            raise ConfigError(f"match_blur_px must be finite and >= 0, got {self.match_blur_px!r}")
        if self.harris_min_response < 0:
            raise ConfigError(
                f"harris_min_response must be >= 0, got {self.harris_min_response!r}"
            )
        if self.sigma_merge not in ("thesis", "inverse_variance"):
            raise ConfigError(
                f"sigma_merge must be 'thesis' or 'inverse_variance', got {self.sigma_merge!r}"
            )

    @property
    def max_travel_m(self) -> float:
        """``d`` of (2.3): the largest travel between two frames."""
        return self.max_speed_m_s / self.frame_rate_hz


@dataclass(frozen=True)
class OdometryUpdate:
    """What one call of :meth:`HybridOdometer.process` returns.

    Attributes:
        stamp_ns: the frame's stamp.
        dx_m, dy_m, dyaw_rad: corrected increment of ``base_link`` in the previous
            ``base_link``.
        yaw_sigma_rad: standard deviation of ``dyaw_rad``.
        fallback: why the wheels supplied the increment, or ``FallbackReason.NONE``.
        pose: ``(x_m, y_m, yaw_rad)`` integrated in ``odom`` after this frame.
        num_sampled, num_far, num_matched, num_inliers: patches at each stage
            (``num_sampled``: corners range-tested).
        cpu_time_s: process CPU time of this call.
    """

    stamp_ns: int
    dx_m: float
    dy_m: float
    dyaw_rad: float
    yaw_sigma_rad: float
    fallback: FallbackReason
    pose: tuple[float, float, float]
    num_sampled: int = 0
    num_far: int = 0
    num_matched: int = 0
    num_inliers: int = 0
    cpu_time_s: float = 0.0

    @property
    def used_vision(self) -> bool:
        """True when the yaw came from the visual tracker."""
        return self.fallback is FallbackReason.NONE

    @property
    def delta(self) -> FloatArray:
        """``(dx_m, dy_m, dyaw_rad)`` as an array ``(3,)``."""
        return np.array([self.dx_m, self.dy_m, self.dyaw_rad])


@dataclass
class OdometerStats:
    """Counters over the odometer's lifetime.

    Attributes:
        frames: frames processed.
        deferred: frames whose increment came from the wheels alone (first frame included).
        by_reason: deferred frames per :class:`FallbackReason` value.
        cpu_time_total_s, cpu_time_last_s: CPU time spent in ``process``.
    """

    frames: int = 0
    deferred: int = 0
    by_reason: dict[str, int] = field(default_factory=dict)
    cpu_time_total_s: float = 0.0
    cpu_time_last_s: float = 0.0

    @property
    def deferred_fraction(self) -> float:
        """Fraction of frames that deferred to wheel odometry."""
        return self.deferred / self.frames if self.frames else 0.0


@dataclass(frozen=True)
class _Prepared:
    spherical: Float32Array
    stereo: tuple[NDArray[np.uint8], NDArray[np.uint8]]  # the pair the range test reads


#: A patch that passed the range test: ``(row, col, horizontal range m)`` in the previous
#: spherical image (range ``inf``: too little disparity to range).
_Patch = tuple[int, int, float]


@dataclass(frozen=True)
class _TrackResult:
    """What tracking one frame pair found (:meth:`HybridOdometer._track`).

    Attributes:
        fallback: why the frame defers to the wheels, or ``FallbackReason.NONE``.
        num_sampled, num_far, num_matched, num_inliers: patches at each stage, as
            :class:`OdometryUpdate` reports them (0 for stages not reached).
        dyaw_rad: the visual yaw increment ``θ_v``; NaN unless ``fallback`` is ``NONE``.
        yaw_sigma_rad: its standard deviation (before the floor); NaN likewise.
    """

    fallback: FallbackReason
    num_sampled: int = 0
    num_far: int = 0
    num_matched: int = 0
    num_inliers: int = 0
    dyaw_rad: float = math.nan
    yaw_sigma_rad: float = math.nan


class HybridOdometer:
    """Wheel odometry with its yaw replaced by visual bearing tracking (thesis ch. 2).

    Args:
        intrinsics: the rectified stereo camera at the resolution frames arrive in.
        mounting: the left camera's mounting on ``base_link`` (with the stereo baseline).
        config: parameters; defaults from the thesis.
    """

    def __init__(
        self,
        intrinsics: CameraIntrinsics,
        mounting: CameraMounting,
        config: OdometerConfig | None = None,
    ) -> None:
        self.config = cfg = config if config is not None else OdometerConfig()
        self.input_intrinsics = intrinsics
        self.mounting = mounting
        work_h = max(
            16, int(round(intrinsics.height_px * cfg.work_width_px / intrinsics.width_px))
        )
        self.work_intrinsics = intrinsics.scaled(cfg.work_width_px, work_h)
        self.spherical = SphericalMap.build(
            self.work_intrinsics, mounting, cfg.band_half_height_rad
        )
        sph = self.spherical
        rows, cols = sph.shape
        if rows < cfg.patch_height_px + 2:
            raise ConfigError(
                f"the spherical band has {rows} rows, fewer than a patch needs "
                f"({cfg.patch_height_px} + 2); raise band_half_height_rad"
            )
        self.frontal_col = float(sph.column_of_theta(0.0))
        half_patch_rad = (cfg.patch_width_px // 2) * sph.a_rad_per_px
        nearest_side_rad = min(self.frontal_col, cols - 1 - self.frontal_col) * sph.a_rad_per_px
        if cfg.theta_max_rad == 0.0:  # the thesis' choice, from the mounting
            theta_max = min(nearest_side_rad - half_patch_rad, cfg.theta_max_cap_rad)
        else:
            theta_max = cfg.theta_max_rad
        if theta_max <= half_patch_rad:
            raise ConfigError(
                f"the frontal direction is not far enough inside the camera's view for "
                f"sampling: theta_max {theta_max:.3f} rad <= half a patch "
                f"({half_patch_rad:.3f} rad); check the mounting yaw"
            )
        self.theta_max_rad = theta_max
        #: r_min of (2.3) at θ_max: nearer patches are dropped.
        self.r_min_m = pt.r_min_m(cfg.max_travel_m, theta_max, sph.a_rad_per_px)
        self.stats = OdometerStats()
        self._prev: _Prepared | None = None
        self._pose = np.zeros(3)

    # ------------------------------------------------------------------ the verb

    def process(self, frame: StereoFrame, wheel_delta: FloatArray) -> OdometryUpdate:
        """Corrected increment for ``frame`` given the wheel increment since the last frame.

        Args:
            frame: rectified stereo pair at the intrinsics' resolution.
            wheel_delta: ``(dx_m, dy_m, dyaw_rad)``, ``(3,)``, of the wheel odometry between
                the previous frame and this one, in the previous ``base_link``.

        Raises:
            FrameError: images of the wrong size, dtype or channel count, or a non-finite
                wheel increment. The odometer's state is unchanged.
        """
        t0 = time.process_time()
        wheel = np.asarray(wheel_delta, dtype=float).reshape(-1)
        if wheel.shape != (3,) or not np.all(np.isfinite(wheel)):
            raise FrameError(f"wheel_delta must be 3 finite numbers, got {wheel_delta!r}")
        cur = self._prepare(frame)
        prev, self._prev = self._prev, cur
        if prev is None:
            track = _TrackResult(FallbackReason.FIRST_FRAME)
        else:
            track = self._track(prev, cur, wheel)
        delta, sigma = self._increment(wheel, track)
        self._integrate(delta)
        cpu = time.process_time() - t0
        self._count(track.fallback, cpu)
        return OdometryUpdate(
            stamp_ns=int(frame.stamp_ns),
            dx_m=float(delta[0]),
            dy_m=float(delta[1]),
            dyaw_rad=float(delta[2]),
            yaw_sigma_rad=float(sigma),
            fallback=track.fallback,
            pose=(float(self._pose[0]), float(self._pose[1]), float(self._pose[2])),
            num_sampled=track.num_sampled,
            num_far=track.num_far,
            num_matched=track.num_matched,
            num_inliers=track.num_inliers,
            cpu_time_s=cpu,
        )

    def reset(self, pose: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
        """Forget the previous frame and restart the integrated pose (counters are kept)."""
        self._prev = None
        self._pose = np.asarray(pose, dtype=float).copy()

    # ------------------------------------------------------------------ steps

    def _prepare(self, frame: StereoFrame) -> _Prepared:
        intr = self.input_intrinsics
        expected = (intr.height_px, intr.width_px)
        full: list[NDArray[np.uint8]] = []
        for side, img in (("left", frame.left), ("right", frame.right)):
            arr: NDArray[Any] = np.asarray(img)
            if arr.shape[:2] != expected or arr.ndim not in (2, 3):
                raise FrameError(
                    f"{side} image has shape {arr.shape}, expected {expected} (grayscale) or "
                    f"{expected + (3,)} (BGR) to match the camera intrinsics"
                )
            if arr.ndim == 3:
                if arr.shape[2] != 3:
                    raise FrameError(f"{side} image has {arr.shape[2]} channels, expected 1 or 3")
                arr = cv2.cvtColor(arr, cv2.COLOR_BGR2GRAY)
            if arr.dtype != np.uint8:
                raise FrameError(f"{side} image has dtype {arr.dtype}, expected uint8")
            full.append(arr)
        w = self.work_intrinsics
        work_shape = (w.height_px, w.width_px)

        def work(arr: NDArray[np.uint8]) -> NDArray[np.uint8]:
            if arr.shape == work_shape:
                return arr
            out = cv2.resize(arr, (w.width_px, w.height_px), interpolation=cv2.INTER_AREA)
            return np.asarray(out, dtype=np.uint8)

        left = work(full[0])
        # Ranged at input resolution, the right image is never needed small: skip its resize.
        if self.config.stereo_at_input_resolution:
            stereo = (full[0], full[1])
        else:
            stereo = (left, work(full[1]))
        spherical = self.spherical.remap(left)
        if self.config.match_blur_px > 0:
            # The parabola through an NCC peak pulls a shift toward the nearest whole pixel
            # the more, the narrower the peak; a turn at a steady rate keeps the same
            # fraction frame after frame, so that pull adds up (0.04 px per frame on the loop
            # drive's turns at 640×480 input). Widening the peak shrinks it.
            spherical = np.asarray(
                cv2.GaussianBlur(spherical, (0, 0), self.config.match_blur_px), np.float32
            )
        return _Prepared(spherical=spherical, stereo=stereo)

    def _sampling_columns(self, shift_cols: float) -> tuple[int, int]:
        """Columns [lo, hi) of the previous spherical image to sample from (§2.3.2–2.3.3)."""
        cols = self.spherical.shape[1]
        hw = self.config.patch_width_px // 2
        half = self.theta_max_rad / self.spherical.a_rad_per_px
        centre = self.frontal_col
        # Would the frontal region's patches scroll off the image under the wheels' turn?
        # Then sample where the frontal region will be in the current frame instead.
        if centre + half + shift_cols > cols - 1 - hw or centre - half + shift_cols < hw:
            centre = self.frontal_col - shift_cols
        lo = int(math.ceil(centre - half))
        hi = int(math.floor(centre + half)) + 1
        return max(lo, 0), min(hi, cols)

    def _parallax(
        self, kept: list[tuple[int, int, float]], theta_hat: float, wheel: FloatArray
    ) -> FloatArray:
        """Per-patch parallax (rad) from the wheel travel and each patch's stereo range.

        (2.3) only bounds the parallax of the patches it keeps to ``θ_p/2``; a sub-pixel NCC
        peak measures it, and with near objects beside the path it is one-sided for many
        frames at a time: a heading drift. The camera travels along the translation (2.4)
        would give for the rotation ``theta_hat`` (the patches' median), plus the swing of
        its mounting offset about ``base_link``.
        """
        half = (theta_hat - wheel[2]) / 2.0
        c, s = math.cos(half), math.sin(half)
        tx, ty = c * wheel[0] - s * wheel[1], s * wheel[0] + c * wheel[1]
        m = self.mounting
        c, s = math.cos(theta_hat), math.sin(theta_hat)
        tx += (c - 1.0) * m.forward_m - s * m.left_m
        ty += s * m.forward_m + (c - 1.0) * m.left_m
        sph = self.spherical
        return np.array(
            [pt.parallax_rad(rng, float(sph.theta_of_column(col)), tx, ty) for _, col, rng in kept]
        )

    def _track(self, prev: _Prepared, cur: _Prepared, wheel: FloatArray) -> _TrackResult:
        """The visual yaw increment from ``prev`` to ``cur`` (steps 2–5 of the module
        docstring), or why the frame defers to the wheels."""
        cfg = self.config
        theta_w_rad = float(wheel[2])
        a = self.spherical.a_rad_per_px
        shift_cols = theta_w_rad / a
        # Sample corners where the patches will still be in view (§2.3.2–2.3.3).
        picks = self._sample(prev, shift_cols)
        if len(picks) < cfg.min_patches:
            return _TrackResult(FallbackReason.BLANK_VIEW, num_sampled=len(picks))
        # The direction of travel in the previous image (the wheels' midpoint heading).
        travel_col = self.frontal_col - theta_w_rad / (2.0 * a)
        if cfg.balance_sides:
            picks = pt.alternate_sides(picks, travel_col)
        # Keep the first num_patches beyond r_min of (2.3).
        far, n_sampled = self._far_patches(prev, picks)
        n_far = len(far)
        if n_far < cfg.min_patches:
            return _TrackResult(FallbackReason.NEAR_FEATURES, n_sampled, n_far)
        # Find each again in the current image.
        kept, est, sig = self._match(prev, cur, far, shift_cols)
        n_matched = len(kept)
        if n_matched < cfg.min_patches:
            return _TrackResult(FallbackReason.POOR_MATCH, n_sampled, n_far, n_matched)
        if cfg.parallax_correction:
            # statistics.median on a handful of floats is ~50x cheaper than np.median.
            est = est - self._parallax(kept, statistics.median(est.tolist()), wheel)
        # Cross-validate by vote (§2.3.4) and merge the inliers.
        inliers = pt.vote(est, a)
        n_in = int(inliers.sum())
        if n_in == 0:
            return _TrackResult(FallbackReason.NO_CONSENSUS, n_sampled, n_far, n_matched)
        theta_v, sigma = self._merge(kept, est, sig, inliers, travel_col)
        return _TrackResult(FallbackReason.NONE, n_sampled, n_far, n_matched, n_in, theta_v, sigma)

    def _sample(self, prev: _Prepared, shift_cols: float) -> list[tuple[int, int]]:
        """Harris corners ``(row, col)`` of the previous spherical image, strongest first."""
        cfg = self.config
        lo, hi = self._sampling_columns(shift_cols)
        # Candidates beyond the first N stand in for patches that the range test drops
        # ("any feature closer than r_min is deemed unfit").
        return pt.sample_patches(
            prev.spherical,
            lo,
            hi,
            cfg.candidate_factor * cfg.num_patches,
            cfg.patch_width_px,
            cfg.patch_height_px,
            cfg.harris_min_response,
        )

    def _far_patches(
        self, prev: _Prepared, picks: list[tuple[int, int]]
    ) -> tuple[list[_Patch], int]:
        """Range test (2.3), by per-patch stereo in the previous frame's planar pair: the
        first ``num_patches`` picks beyond ``r_min``, and how many picks were tested."""
        # Range from the pair as it arrived: at 160 px a 50 m feature has under a pixel of
        # disparity, and the parabola pulls such disparities toward whole pixels (ranges too
        # short, parallax over-corrected); matching a few more pixels costs little.
        st_scale = prev.stereo[0].shape[1] / self.work_intrinsics.width_px
        far: list[_Patch] = []
        n_sampled = 0
        for r, c in picks:
            if len(far) == self.config.num_patches:
                break
            n_sampled += 1
            patch = self._ranged_patch(prev, r, c, st_scale)
            if patch is not None:
                far.append(patch)
        return far, n_sampled

    def _ranged_patch(self, prev: _Prepared, r: int, c: int, st_scale: float) -> _Patch | None:
        """The patch at ``(r, c)`` with its horizontal range, or None when it is nearer than
        ``r_min`` of (2.3) at its bearing or its stereo is unreliable."""
        cfg = self.config
        sph = self.spherical
        intr = self.work_intrinsics
        u, v = float(sph.map_u[r, c]), float(sph.map_v[r, c])
        depth = self._stereo_depth_m(prev, u, v, st_scale)
        ray_scale = math.sqrt(
            1.0 + ((u - intr.cx_px) / intr.fx_px) ** 2 + ((v - intr.cy_px) / intr.fy_px) ** 2
        )
        theta = abs(float(sph.theta_of_column(c)))
        r_min = (
            self.r_min_m
            if theta <= self.theta_max_rad
            else pt.r_min_m(cfg.max_travel_m, theta, sph.a_rad_per_px)
        )
        dist = depth * ray_scale
        if not dist >= r_min:  # NaN (unreliable stereo) compares False: dropped
            return None
        phi = sph.phi_o_rad + sph.a_rad_per_px * r
        # Too little disparity to range: treat as far rather than correct by noise.
        disparity_px = intr.fx_px * self.mounting.baseline_m / depth
        ranged = disparity_px >= cfg.parallax_min_disparity_px
        return r, c, dist * math.cos(phi) if ranged else math.inf

    def _stereo_depth_m(self, prev: _Prepared, u: float, v: float, st_scale: float) -> float:
        """Depth (m) at working-image pixel ``(u, v)`` by stereo matching in ``prev``'s pair,
        ``st_scale`` times the working resolution; NaN when unreliable."""
        cfg = self.config
        intr = self.work_intrinsics
        # The window keeps half the working window's angular size to stay cheap.
        return pt.stereo_range_m(
            prev.stereo[0],
            prev.stereo[1],
            (u + 0.5) * st_scale - 0.5,
            (v + 0.5) * st_scale - 0.5,
            intr.fx_px * st_scale,
            self.mounting.baseline_m,
            int(round(cfg.stereo_max_disparity_px * st_scale)),
            max(cfg.stereo_half_width_px, int(round(cfg.stereo_half_width_px * st_scale / 2))),
            max(cfg.stereo_half_height_px, int(round(cfg.stereo_half_height_px * st_scale / 2))),
            cfg.stereo_min_ncc,
        )

    def _match(
        self, prev: _Prepared, cur: _Prepared, far: list[_Patch], shift_cols: float
    ) -> tuple[list[_Patch], FloatArray, FloatArray]:
        """NCC search of each patch in the current spherical image (§2.3.3): the patches
        found with enough correlation, their yaw estimates (rad) and σ (rad)."""
        cfg = self.config
        a = self.spherical.a_rad_per_px
        hw = cfg.patch_width_px // 2
        estimates: list[float] = []
        sigmas: list[float] = []
        kept: list[_Patch] = []
        for r, c, rng_m in far:
            # Window spans the previous and the wheel-predicted position, plus half a patch
            # on all sides (§2.3.3).
            c0 = int(math.floor(min(c, c + shift_cols))) - hw - hw
            c1 = int(math.ceil(max(c, c + shift_cols))) + hw + hw + 1
            found = pt.track_patch(
                prev.spherical,
                cur.spherical,
                r,
                c,
                cfg.patch_width_px,
                cfg.patch_height_px,
                c0,
                c1,
                cfg.symmetric_subpixel,
            )
            if found is None:
                continue
            shift_px, peak, sigma_px = found
            if peak < cfg.min_ncc or not math.isfinite(sigma_px):
                continue
            estimates.append(shift_px * a)
            sigmas.append(sigma_px * a)
            kept.append((r, c, rng_m))
        return kept, np.array(estimates), np.array(sigmas)

    def _merge(
        self,
        kept: list[_Patch],
        est: FloatArray,
        sig: FloatArray,
        inliers: NDArray[np.bool_],
        travel_col: float,
    ) -> tuple[float, float]:
        """The inliers' yaw (rad) and its σ (rad): they agree to within θ_p, so they are
        weighted by their peak sharpness (and by side of travel with ``balance_sides``)."""
        cfg = self.config
        w = 1.0 / sig[inliers] ** 2
        if cfg.balance_sides:
            cols_in = np.array([col for _, col, _ in kept])[inliers]
            w = pt.balance_weights(w, cols_in < travel_col)
        theta_v = float(np.sum(w * est[inliers]) / np.sum(w))
        return theta_v, pt.merge_sigmas(sig[inliers], cfg.sigma_merge)

    def _increment(self, wheel: FloatArray, track: _TrackResult) -> tuple[FloatArray, float]:
        """The frame's increment ``(dx_m, dy_m, dyaw_rad)`` and its yaw σ (rad): the wheels'
        when the frame defers to them, else the visual yaw with the translation of (2.4)."""
        cfg = self.config
        if track.fallback is not FallbackReason.NONE:
            return wheel.copy(), cfg.fallback_yaw_sigma_rad
        theta_v = track.dyaw_rad
        # (2.4) wants the wheel translation with the wheel's full rotation applied; a wheel
        # increment in the previous frame follows the midpoint convention (travel along
        # θ_w/2), so rotate by the other θ_w/2 first.
        half_w = wheel[2] / 2.0
        c, s = math.cos(half_w), math.sin(half_w)
        dp_end = np.array([c * wheel[0] - s * wheel[1], s * wheel[0] + c * wheel[1]])
        dp = pt.localize(np.zeros(2), theta_v, float(wheel[2]), dp_end)
        return np.array([dp[0], dp[1], theta_v]), max(track.yaw_sigma_rad, cfg.yaw_sigma_floor_rad)

    def _count(self, fallback: FallbackReason, cpu_s: float) -> None:
        """Add one frame to :attr:`stats`."""
        st = self.stats
        st.frames += 1
        st.cpu_time_total_s += cpu_s
        st.cpu_time_last_s = cpu_s
        if fallback is not FallbackReason.NONE:
            st.deferred += 1
            st.by_reason[fallback.value] = st.by_reason.get(fallback.value, 0) + 1

    def _integrate(self, delta: FloatArray) -> None:
        x, y, yaw = self._pose
        c, s = math.cos(yaw), math.sin(yaw)
        new_yaw = (yaw + delta[2] + math.pi) % (2.0 * math.pi) - math.pi
        self._pose = np.array(
            [x + c * delta[0] - s * delta[1], y + s * delta[0] + c * delta[1], new_yaw]
        )
