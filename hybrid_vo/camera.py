"""Camera model and the spherical look-up table of thesis §2.3.1, eqs. (2.1)–(2.2).

Frames and conventions:

* ``base_link`` follows REP-103: x forward, y left, z up. Robot yaw is positive to the left.
* The camera's optical frame is x right, y down, z forward (OpenCV, ROS ``*_optical``).
  Pixel ``(u, v)`` = (column, row) with pixel centres at integer coordinates; the view ray
  of a pixel in the optical frame is ``((u − cx)/fx, (v − cy)/fy, 1)``.
* The mounting rotates the optical frame into ``base_link``: first the fixed axis swap
  (optical z → base x, optical x → base −y, optical y → base −z), then roll about x,
  pitch about y, yaw about z of ``base_link`` (``R = Rz(yaw) Ry(pitch) Rx(roll)``). In
  REP-103 a positive pitch tilts the camera **down**, a positive yaw turns it **left**.
* Spherical image (thesis Fig. 2.1): row ``k`` and column ``l`` cover a fixed amount of
  vehicle-relative pitch φ and yaw θ. To keep (2.1)–(2.2) literal with rows growing
  downward and columns growing to the right, the spherical image uses φ = angle **below**
  the horizon and θ = bearing to the **right** of the robot's forward axis (θ = −REP-103
  yaw of the ray). A far feature therefore moves by ``+Δψ / a`` columns when the robot turns
  left by Δψ.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from hybrid_vo.errors import ConfigError

FloatArray = NDArray[np.float64]
Float32Array = NDArray[np.float32]
BoolArray = NDArray[np.bool_]

# Optical frame (x right, y down, z forward) -> base_link (x forward, y left, z up).
_OPTICAL_TO_BASE = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _finite_positive(name: str, value: float) -> None:
    if not math.isfinite(value) or value <= 0.0:
        raise ConfigError(f"{name} must be finite and > 0, got {value!r}")


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of a rectified camera, in pixels.

    Attributes:
        width_px, height_px: image size.
        fx_px, fy_px: focal lengths.
        cx_px, cy_px: principal point (pixel centres at integer coordinates).
    """

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float

    def __post_init__(self) -> None:
        for name in ("width_px", "height_px"):
            value = getattr(self, name)
            if not isinstance(value, int | np.integer) or value < 8:
                raise ConfigError(f"{name} must be an integer >= 8, got {value!r}")
        for name in ("fx_px", "fy_px"):
            _finite_positive(name, float(getattr(self, name)))
        for name in ("cx_px", "cy_px"):
            if not math.isfinite(float(getattr(self, name))):
                raise ConfigError(f"{name} must be finite, got {getattr(self, name)!r}")

    def scaled(self, width_px: int, height_px: int) -> CameraIntrinsics:
        """The same camera resampled to ``width_px × height_px`` (as ``cv2.resize`` does).

        Pixel centres map as ``u' = (u + 0.5)·s − 0.5``, hence the half-pixel terms.
        """
        sx = width_px / self.width_px
        sy = height_px / self.height_px
        return CameraIntrinsics(
            width_px=int(width_px),
            height_px=int(height_px),
            fx_px=self.fx_px * sx,
            fy_px=self.fy_px * sy,
            cx_px=(self.cx_px + 0.5) * sx - 0.5,
            cy_px=(self.cy_px + 0.5) * sy - 0.5,
        )

    def matrix(self) -> FloatArray:
        """The 3×3 camera matrix K."""
        return np.array(
            [[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]]
        )


@dataclass(frozen=True)
class CameraMounting:
    """Where the (left) stereo camera sits on the robot, relative to ``base_link``.

    Attributes:
        yaw_rad: rotation about base z; positive turns the camera to the left.
        pitch_rad: rotation about base y; positive tilts the camera down (REP-103).
        roll_rad: rotation about the camera's forward axis; positive rolls it to the right.
        height_m: height of the optical centre above the ground plane.
        baseline_m: stereo baseline; the right camera sits ``baseline_m`` along the left
            camera's optical +x axis.
        forward_m, left_m: position of the left optical centre in ``base_link`` (x, y).
    """

    yaw_rad: float = 0.0
    pitch_rad: float = 0.0
    roll_rad: float = 0.0
    height_m: float = 1.0
    baseline_m: float = 0.12
    forward_m: float = 0.0
    left_m: float = 0.0

    def __post_init__(self) -> None:
        for name in ("yaw_rad", "pitch_rad", "roll_rad", "forward_m", "left_m"):
            if not math.isfinite(float(getattr(self, name))):
                raise ConfigError(f"{name} must be finite, got {getattr(self, name)!r}")
        if abs(self.pitch_rad) >= math.pi / 2 or abs(self.roll_rad) >= math.pi / 2:
            raise ConfigError(
                f"pitch_rad and roll_rad must lie in (-pi/2, pi/2) for a camera that sees "
                f"the horizon, got pitch {self.pitch_rad!r}, roll {self.roll_rad!r}"
            )
        _finite_positive("height_m", float(self.height_m))
        _finite_positive("baseline_m", float(self.baseline_m))

    def rotation_base_from_optical(self) -> FloatArray:
        """3×3 rotation taking optical-frame vectors into ``base_link``."""
        cy, sy = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        cp, sp = math.cos(self.pitch_rad), math.sin(self.pitch_rad)
        cr, sr = math.cos(self.roll_rad), math.sin(self.roll_rad)
        rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
        ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
        rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
        return rz @ ry @ rx @ _OPTICAL_TO_BASE


def pixel_rays_base(intr: CameraIntrinsics, mount: CameraMounting) -> FloatArray:
    """Unit view rays of every pixel in ``base_link``, shape ``(height_px, width_px, 3)``."""
    u = np.arange(intr.width_px, dtype=float)
    v = np.arange(intr.height_px, dtype=float)
    uu, vv = np.meshgrid(u, v)
    rays = np.stack(
        [(uu - intr.cx_px) / intr.fx_px, (vv - intr.cy_px) / intr.fy_px, np.ones_like(uu)],
        axis=-1,
    )
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    out: FloatArray = rays @ mount.rotation_base_from_optical().T
    return out


def ray_angles(rays_base: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(φ, θ) of rays ``(..., 3)`` in ``base_link``: φ below the horizon, θ to the right."""
    x, y, z = rays_base[..., 0], rays_base[..., 1], rays_base[..., 2]
    phi = -np.arctan2(z, np.hypot(x, y))
    theta = -np.arctan2(y, x)
    return phi, theta


def rays_from_angles(phi_rad: FloatArray, theta_rad: FloatArray) -> FloatArray:
    """Unit rays ``(..., 3)`` in ``base_link`` for φ (below horizon) and θ (to the right)."""
    cphi = np.cos(phi_rad)
    return np.stack(
        [cphi * np.cos(theta_rad), -cphi * np.sin(theta_rad), -np.sin(phi_rad)], axis=-1
    )


def project_base_rays(
    intr: CameraIntrinsics, mount: CameraMounting, rays_base: FloatArray
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Pixels ``(u, v)`` seen along base-frame rays ``(..., 3)``, and whether they are in view."""
    cam = rays_base @ mount.rotation_base_from_optical()  # R^T r, batched
    z = cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intr.fx_px * cam[..., 0] / z + intr.cx_px
        v = intr.fy_px * cam[..., 1] / z + intr.cy_px
    inside = (
        (z > 1e-9)
        & (u >= 0.0)
        & (u <= intr.width_px - 1.0)
        & (v >= 0.0)
        & (v <= intr.height_px - 1.0)
    )
    return u, v, inside


@dataclass(frozen=True)
class SphericalMap:
    """The look-up table of eqs. (2.1)–(2.2), built once per calibration.

    ``k = (φ − φ_o)/a`` and ``l = (θ − θ_o)/a``: ``a`` is the radians per pixel of the
    planar image's centre pixel, ``(φ_o, θ_o)`` the pitch and yaw of the upper-left pixel of
    the spherical image. The spherical image covers the horizon band ``|φ| ≤ band`` and the
    widest yaw range over which every row of the band is inside the camera image, so that
    it has no blank pixels.

    Attributes:
        intrinsics: camera the table reads from (the working resolution).
        mounting: the camera's mounting on the robot.
        a_rad_per_px: radians per spherical pixel.
        phi_o_rad, theta_o_rad: (φ, θ) of spherical pixel (0, 0).
        map_u, map_v: float32 ``(rows, cols)``: the planar pixel each spherical pixel reads.
    """

    intrinsics: CameraIntrinsics
    mounting: CameraMounting
    a_rad_per_px: float
    phi_o_rad: float
    theta_o_rad: float
    map_u: Float32Array
    map_v: Float32Array

    @classmethod
    def build(
        cls, intr: CameraIntrinsics, mount: CameraMounting, band_half_height_rad: float
    ) -> SphericalMap:
        """Precompute the table for a camera; raises ConfigError if the band is not in view."""
        _finite_positive("band_half_height_rad", band_half_height_rad)
        # Horizontal subtense of the principal pixel (thesis: "radians-per-pixel of the centre
        # pixel in the planar image").
        a = 2.0 * math.atan(0.5 / intr.fx_px)
        rows = int(math.floor(2.0 * band_half_height_rad / a)) + 1
        phi_o = -0.5 * (rows - 1) * a
        # Yaw extent: scan a generous grid of columns, keep the longest run whose whole
        # column (every band row) projects inside the image.
        half_fov = math.pi * 0.95
        cols_all = int(2 * half_fov / a) + 1
        theta_all = -half_fov + a * np.arange(cols_all)
        phi = phi_o + a * np.arange(rows)
        pp, tt = np.meshgrid(phi, theta_all, indexing="ij")
        _, _, inside = project_base_rays(intr, mount, rays_from_angles(pp, tt))
        col_ok = inside.all(axis=0)
        best_len, best_start, run_start = 0, 0, -1
        for i, ok in enumerate(np.append(col_ok, False)):
            if ok and run_start < 0:
                run_start = i
            elif not ok and run_start >= 0:
                if i - run_start > best_len:
                    best_len, best_start = i - run_start, run_start
                run_start = -1
        if best_len < 16:
            raise ConfigError(
                f"the horizon band (±{band_half_height_rad:.3f} rad) is not in view of the "
                f"camera: only {best_len} full spherical columns (need >= 16); check the "
                f"mounting pitch/roll and band_half_height_rad"
            )
        theta_o = float(theta_all[best_start])
        theta = theta_o + a * np.arange(best_len)
        pp, tt = np.meshgrid(phi, theta, indexing="ij")
        u, v, _ = project_base_rays(intr, mount, rays_from_angles(pp, tt))
        return cls(
            intrinsics=intr,
            mounting=mount,
            a_rad_per_px=a,
            phi_o_rad=phi_o,
            theta_o_rad=theta_o,
            map_u=u.astype(np.float32),
            map_v=v.astype(np.float32),
        )

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the spherical image."""
        rows, cols = self.map_u.shape
        return int(rows), int(cols)

    def forward(self, u: Any, v: Any) -> tuple[FloatArray, FloatArray]:
        """Eqs. (2.1)–(2.2): spherical ``(k, l)`` of planar pixels ``(u, v)`` (any shape)."""
        intr = self.intrinsics
        u_arr = np.asarray(u, dtype=float)
        v_arr = np.asarray(v, dtype=float)
        rays = np.stack(
            [
                (u_arr - intr.cx_px) / intr.fx_px,
                (v_arr - intr.cy_px) / intr.fy_px,
                np.ones_like(u_arr),
            ],
            axis=-1,
        )
        phi, theta = ray_angles(rays @ self.mounting.rotation_base_from_optical().T)
        k = (phi - self.phi_o_rad) / self.a_rad_per_px  # (2.1)
        l_col = (theta - self.theta_o_rad) / self.a_rad_per_px  # (2.2)
        return k, l_col

    def theta_of_column(self, l_col: Any) -> FloatArray:
        """Bearing θ (rad, to the right of forward) of spherical column(s) ``l``."""
        return np.asarray(self.theta_o_rad + self.a_rad_per_px * np.asarray(l_col, float))

    def column_of_theta(self, theta_rad: Any) -> FloatArray:
        """Spherical column(s) of bearing(s) θ (rad, to the right of forward)."""
        return np.asarray((np.asarray(theta_rad, float) - self.theta_o_rad) / self.a_rad_per_px)

    def remap(self, image: NDArray[Any]) -> Float32Array:
        """The spherical image (float32, ``shape``) of a planar image at the table's size."""
        if image.shape[:2] != (self.intrinsics.height_px, self.intrinsics.width_px):
            raise ConfigError(
                f"image is {image.shape[1]}x{image.shape[0]} but the spherical table was "
                f"built for {self.intrinsics.width_px}x{self.intrinsics.height_px}"
            )
        src = np.asarray(image, dtype=np.float32)
        out: Float32Array = np.asarray(
            cv2.remap(src, self.map_u, self.map_v, cv2.INTER_LINEAR), dtype=np.float32
        )
        return out
