"""A synthetic stereo world for testing and benchmarking the hybrid odometer.

Deterministic from a seed. What the robot would record while driving a ground-truth planar
trajectory through it:

* rectified stereo pairs (``uint8`` grayscale, ``(height_px, width_px)``) rendered by ray
  casting a cheap scene: far textured scenery on a cylinder of radius ``far_radius_m``
  around the origin with a ragged skyline (the features the odometer should track), a
  textured ground plane ``z = 0``, and near textured vertical cylinders (posts, trees) that
  the range test (2.3) must reject; a blank sky above;
* wheel odometry increments with noise and configurable slip (thesis §2.2.1): slow heading
  drift and sudden hallucinated turns;
* NavSatFix-like GPS samples with noise and dropouts (plain dataclasses, no ROS types);
* loop-closure measurements wherever the path revisits itself;
* camera info.

Frames: world is ENU-like (x east, y north, z up), robot poses are planar ``(x_m, y_m,
yaw_rad)`` of ``base_link`` in the world; increments are ``(dx_m, dy_m, dyaw_rad)`` of the
new pose expressed in the previous ``base_link`` (``T_prev⁻¹ T_new``).

Rendering is vectorized numpy + ``cv2.remap``; at 160×120 a stereo pair takes about a
millisecond, at 640×480 some tens of milliseconds.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from h2o_slam.core.geometry import planar_between, planar_compose, wrap_angle
from hybrid_vo.camera import CameraIntrinsics, CameraMounting, pixel_rays_base
from hybrid_vo.errors import ConfigError
from hybrid_vo.frames import StereoFrame
from msg_adapters.gps import Datum

FloatArray = NDArray[np.float64]
ImageU8 = NDArray[np.uint8]

#: NavSatStatus-like status values.
STATUS_NO_FIX = -1
STATUS_FIX = 0

#: Latitude (deg), longitude (deg) and ellipsoidal altitude (m) of the world's ENU origin.
GPS_DATUM = (37.4275, -122.1697, 30.0)


# ----------------------------------------------------------------------------- geometry


def integrate(start: FloatArray, increments: FloatArray) -> FloatArray:
    """Poses ``(N+1, 3)`` from a start pose and ``(N, 3)`` increments."""
    poses = np.empty((len(increments) + 1, 3))
    poses[0] = start
    for i, d in enumerate(increments):
        poses[i + 1] = planar_compose(poses[i], d)
    return poses


# ----------------------------------------------------------------------------- textures


def _periodic_noise(rng: np.random.Generator, shape: tuple[int, int], beta: float) -> FloatArray:
    """Zero-mean unit-variance noise with a 1/f^beta spectrum, periodic in both axes."""
    white = rng.standard_normal(shape)
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.rfftfreq(shape[1])[None, :]
    f = np.hypot(fy, fx)
    f[0, 0] = 1.0
    spec = np.fft.rfft2(white) / f**beta
    spec[0, 0] = 0.0
    out = np.fft.irfft2(spec, s=shape)
    return np.asarray((out - out.mean()) / (out.std() + 1e-12))


def _to_u8_range(noise: FloatArray, lo: float, hi: float) -> NDArray[np.float32]:
    x = np.clip(0.5 + noise / 5.0, 0.0, 1.0)
    return (lo + (hi - lo) * x).astype(np.float32)


@dataclass(frozen=True)
class NearObject:
    """A textured vertical cylinder standing on the ground (a post, a tree trunk, a person).

    Attributes:
        x_m, y_m: axis position in the world.
        radius_m, height_m: size.
        texture_offset: which part of the shared object texture it wears (0..1).
    """

    x_m: float
    y_m: float
    radius_m: float
    height_m: float
    texture_offset: float = 0.0


@dataclass(frozen=True)
class WorldConfig:
    """Scene parameters.

    Attributes:
        seed: every texture and every noise draw follows from it.
        far_radius_m: radius of the scenery cylinder around the world origin.
        far_height_m: mean height of the skyline; ``skyline_jitter_m`` its ragged amplitude.
        ground_cell_m: ground texture pixel size; the ground texture wraps every
            ``ground_texture_px · ground_cell_m`` metres.
        pixel_noise: standard deviation of additive image noise (grey levels).
    """

    seed: int = 0
    far_radius_m: float = 150.0
    far_height_m: float = 22.0
    skyline_jitter_m: float = 6.0
    far_texture_px: tuple[int, int] = (512, 4096)
    ground_texture_px: int = 512
    ground_cell_m: float = 0.04
    pixel_noise: float = 1.5
    sky_level: float = 205.0

    def __post_init__(self) -> None:
        if self.far_radius_m <= 5.0:
            raise ConfigError(f"far_radius_m must be > 5 m, got {self.far_radius_m!r}")
        if self.far_height_m <= self.skyline_jitter_m or self.skyline_jitter_m < 0:
            raise ConfigError(
                f"need far_height_m > skyline_jitter_m >= 0, got {self.far_height_m!r}, "
                f"{self.skyline_jitter_m!r}"
            )
        if self.ground_cell_m <= 0 or self.pixel_noise < 0:
            raise ConfigError("ground_cell_m must be > 0 and pixel_noise >= 0")


class World:
    """The scene and a renderer for one stereo camera (see module docstring)."""

    def __init__(
        self,
        config: WorldConfig,
        objects: tuple[NearObject, ...],
        intrinsics: CameraIntrinsics,
        mounting: CameraMounting,
    ) -> None:
        self.config = config
        self.objects = objects
        self.intrinsics = intrinsics
        self.mounting = mounting
        rng = np.random.default_rng(config.seed)
        fh, fw = config.far_texture_px
        far = _periodic_noise(rng, (fh, fw), 1.1) + 0.6 * _periodic_noise(rng, (fh, fw), 0.6)
        self._skyline_m = config.far_height_m + config.skyline_jitter_m * np.clip(
            _periodic_noise(rng, (1, fw), 1.4)[0] / 2.5, -1.0, 1.0
        )
        gsz = config.ground_texture_px
        ground = _periodic_noise(rng, (gsz, gsz), 0.9)
        obj = _periodic_noise(rng, (256, 1024), 0.8)
        # Angular size of one pixel decides how much each texture must be pre-blurred so
        # that a low-resolution camera does not alias (a real lens + sensor integrates).
        rad_per_px = 1.0 / intrinsics.fx_px
        far_rad_per_texel = 2.0 * math.pi / fw
        blur = max(0.0, 0.5 * rad_per_px / far_rad_per_texel)
        self._far_tex = _blur_wrap(_to_u8_range(far, 35.0, 150.0), blur)
        o = _to_u8_range(obj, 60.0, 240.0)
        self._obj_levels = [o, _blur_wrap(o, 1.5), _blur_wrap(o, 4.0), _blur_wrap(o, 10.0)]
        g = _to_u8_range(ground, 70.0, 190.0)
        self._ground_levels = [g, _blur_wrap(g, 2.0), _blur_wrap(g, 6.0)]
        self._rays = pixel_rays_base(intrinsics, mounting).astype(np.float32)
        horiz = np.hypot(self._rays[..., 0], self._rays[..., 1])
        self._bearing_x = (self._rays[..., 0] / horiz).astype(np.float32)
        self._bearing_y = (self._rays[..., 1] / horiz).astype(np.float32)
        bearings = np.arctan2(self._rays[..., 1], self._rays[..., 0])
        self._max_bearing = float(np.max(np.abs(bearings)))
        r_bo = mounting.rotation_base_from_optical()
        self._left_offset = np.array([mounting.forward_m, mounting.left_m, mounting.height_m])
        self._right_offset = self._left_offset + r_bo @ np.array([mounting.baseline_m, 0.0, 0.0])
        self._rad_per_px = rad_per_px

    def render_stereo(self, pose: FloatArray, frame_index: int = 0) -> tuple[ImageU8, ImageU8]:
        """Left and right ``uint8`` images ``(height_px, width_px)`` from a planar pose.

        ``frame_index`` seeds the pixel noise, so renders are reproducible.
        """
        rng = np.random.default_rng((self.config.seed, frame_index))
        return (
            self._render(pose, self._left_offset, rng),
            self._render(pose, self._right_offset, rng),
        )

    def _render(
        self, pose: FloatArray, offset_base: FloatArray, rng: np.random.Generator
    ) -> ImageU8:
        cfg = self.config
        c, s = math.cos(pose[2]), math.sin(pose[2])
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=np.float32)
        d = self._rays @ rot.T
        ox = pose[0] + c * offset_base[0] - s * offset_base[1]
        oy = pose[1] + s * offset_base[0] + c * offset_base[1]
        oz = offset_base[2]
        dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
        # Far cylinder: |o + t d|_xy = R, the camera is inside, take the positive root.
        a2 = dx * dx + dy * dy + 1e-12
        b = ox * dx + oy * dy
        cc = ox * ox + oy * oy - cfg.far_radius_m**2
        t_far = (-b + np.sqrt(b * b - a2 * cc)) / a2
        hx, hy = ox + t_far * dx, oy + t_far * dy
        hz = oz + t_far * dz
        bearing = np.arctan2(hy, hx) % (2.0 * np.pi)
        fh, fw = self._far_tex.shape
        col = (bearing * (fw / (2.0 * np.pi))).astype(np.float32)
        sky_top = self._skyline_m[np.clip(col.astype(np.int64), 0, fw - 1)]
        row = ((1.0 - hz / (cfg.far_height_m + cfg.skyline_jitter_m)) * (fh - 1)).astype(
            np.float32
        )
        img: NDArray[np.float32] = np.asarray(
            cv2.remap(self._far_tex, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP),
            dtype=np.float32,
        )
        img = np.where(hz > sky_top, np.float32(cfg.sky_level) - 10.0 * dz, img).astype(np.float32)
        depth = np.where(hz > sky_top, np.inf, t_far)
        # Ground plane z = 0, with a texture level chosen by the pixel footprint.
        with np.errstate(divide="ignore", invalid="ignore"):
            t_g = np.where(dz < -1e-6, -oz / dz, np.inf)
        hit_g = t_g < depth
        if np.any(hit_g):
            # Texture look-ups for the ground pixels only, as an (N, 1) map per level: the
            # full-image remap of every level was most of the render time.
            t_hit = t_g[hit_g]
            dx_g, dy_g, dz_g = dx[hit_g], dy[hit_g], dz[hit_g]
            gx = ((ox + t_hit * dx_g) / cfg.ground_cell_m).astype(np.float32)
            gy = ((oy + t_hit * dy_g) / cfg.ground_cell_m).astype(np.float32)
            footprint = t_hit * self._rad_per_px / np.maximum(-dz_g, 0.05) / cfg.ground_cell_m
            level = np.where(footprint < 2.0, 0, np.where(footprint < 8.0, 1, 2))
            ground = np.zeros(t_hit.shape, dtype=np.float32)
            for i, tex in enumerate(self._ground_levels):
                sel = level == i
                if np.any(sel):
                    ground[sel] = _remap_points(tex, gx[sel], gy[sel])
            img = img.copy()
            img[hit_g] = ground
            depth = np.where(hit_g, t_g, depth)
        for obj in self.objects:
            img, depth = self._render_object(obj, ox, oy, oz, float(pose[2]), d, img, depth)
        if cfg.pixel_noise > 0:
            img = img + rng.normal(0.0, cfg.pixel_noise, img.shape).astype(np.float32)
        out: ImageU8 = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        return out

    def _render_object(
        self,
        obj: NearObject,
        ox: float,
        oy: float,
        oz: float,
        yaw: float,
        d: NDArray[np.float32],
        img: NDArray[np.float32],
        depth: FloatArray,
    ) -> tuple[NDArray[np.float32], FloatArray]:
        px, py = ox - obj.x_m, oy - obj.y_m
        dist = math.hypot(px, py)
        if dist <= obj.radius_m:
            return img, depth  # the camera is inside the object: nothing sensible to draw
        dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
        # Cheap cull: only pixels whose ray bearing lies within the object's angular extent.
        to_obj = math.atan2(-py, -px)
        half = math.asin(min(1.0, obj.radius_m / dist)) + 1e-3
        # As a dot product with the rays' fixed horizontal bearings in base_link (the pose only
        # turns them by its yaw): one multiply-add per pixel instead of atan2 and a wrap.
        rel = to_obj - yaw
        if abs(float(wrap_angle(np.asarray(rel)))) - half > self._max_bearing:
            return img, depth  # outside the camera's horizontal field of view
        cand = (
            self._bearing_x * np.float32(math.cos(rel))
            + self._bearing_y * np.float32(math.sin(rel))
            > np.float32(math.cos(half))
        )
        if not np.any(cand):
            return img, depth
        rows, cols = np.nonzero(cand)
        ddx, ddy, ddz = dx[rows, cols], dy[rows, cols], dz[rows, cols]
        a2 = ddx * ddx + ddy * ddy + 1e-12
        b = px * ddx + py * ddy
        disc = b * b - a2 * (dist * dist - obj.radius_m**2)
        ok = disc >= 0
        t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a2
        hz = oz + t * ddz
        ok &= (t > 0) & (hz >= 0) & (hz <= obj.height_m) & (t < depth[rows, cols])
        if not np.any(ok):
            return img, depth
        rows, cols, t, hz = rows[ok], cols[ok], t[ok], hz[ok]
        hx = px + t * ddx[ok]
        hy = py + t * ddy[ok]
        # Texture level by pixel footprint in texels (1 texel = 1 cm), as a lens would blur.
        footprint = dist * self._rad_per_px / 0.01
        level = 0 if footprint < 1.5 else 1 if footprint < 4 else 2 if footprint < 10 else 3
        tex = self._obj_levels[level]
        th, tw = tex.shape
        # Texture wraps around the circumference at 1 texel per ~1 cm of arc.
        around = (np.arctan2(hy, hx) + math.pi) * obj.radius_m / 0.01 + obj.texture_offset * tw
        # Bilinear lookup by hand (cv2.remap caps maps at 32767 pixels): a nearest-texel
        # lookup snaps the texture to whole 1 cm texels, which at 640×480 and a few metres
        # is a large part of a pixel and makes the texture jitter as the camera moves.
        vals = _bilinear_wrap(tex, np.asarray(around, dtype=np.float64), hz / 0.01)
        img = img.copy()
        depth = depth.copy()
        img[rows, cols] = vals
        depth[rows, cols] = t
        return img, depth


def _remap_points(
    tex: NDArray[np.float32], x: NDArray[np.float32], y: NDArray[np.float32]
) -> NDArray[np.float32]:
    """``cv2.remap`` (bilinear, wrapping) of ``tex`` at the points ``(x, y)``, shape ``(N,)``.

    The points go in as rows of 1024 (padded), since remap refuses maps of 32767 rows or more.
    """
    n = x.size
    width = 1024
    rows = -(-n // width)
    mx = np.zeros(rows * width, dtype=np.float32)
    my = np.zeros(rows * width, dtype=np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(
        tex,
        mx.reshape(rows, width),
        my.reshape(rows, width),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_WRAP,
    )
    vals: NDArray[np.float32] = np.asarray(out, dtype=np.float32).reshape(-1)[:n]
    return vals


def _bilinear_wrap(
    tex: NDArray[np.float32], x: FloatArray, y: FloatArray
) -> NDArray[np.float32]:
    """``tex`` sampled bilinearly at ``(x, y)`` (texel units, centres at integers), wrapping."""
    th, tw = tex.shape
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0).astype(np.float32)
    fy = (y - y0).astype(np.float32)
    u0 = x0.astype(np.int64) % tw
    v0 = y0.astype(np.int64) % th
    u1 = (u0 + 1) % tw
    v1 = (v0 + 1) % th
    top = tex[v0, u0] * (1.0 - fx) + tex[v0, u1] * fx
    bottom = tex[v1, u0] * (1.0 - fx) + tex[v1, u1] * fx
    out: NDArray[np.float32] = (top * (1.0 - fy) + bottom * fy).astype(np.float32)
    return out


def _blur_wrap(tex: NDArray[np.float32], sigma_px: float) -> NDArray[np.float32]:
    """Gaussian blur of a texture that wraps around in both axes (done in Fourier space)."""
    if sigma_px <= 0.25:
        return tex
    fy = np.fft.fftfreq(tex.shape[0])[:, None]
    fx = np.fft.rfftfreq(tex.shape[1])[None, :]
    gain = np.exp(-2.0 * (math.pi * sigma_px) ** 2 * (fx * fx + fy * fy))
    return np.fft.irfft2(np.fft.rfft2(tex) * gain, s=tex.shape).astype(np.float32)


# ----------------------------------------------------------------------------- sensors


@dataclass(frozen=True)
class CameraInfo:
    """What a ``sensor_msgs/CameraInfo`` pair says about the rectified stereo camera.

    Attributes:
        intrinsics: pinhole model of both rectified images.
        mounting: the left camera's mounting on ``base_link``.
        frame_id: optical frame of the left camera.
    """

    intrinsics: CameraIntrinsics
    mounting: CameraMounting
    frame_id: str = "camera_left_optical"

    def projection_right(self) -> FloatArray:
        """3×4 projection matrix P of the right camera (``Tx = −fx·baseline``), as ROS has."""
        p = np.zeros((3, 4))
        p[:, :3] = self.intrinsics.matrix()
        p[0, 3] = -self.intrinsics.fx_px * self.mounting.baseline_m
        return p


@dataclass(frozen=True)
class WheelSlipConfig:
    """Wheel-odometry error model (thesis §2.2.1).

    Attributes:
        scale_sigma: relative noise of each step's travelled distance.
        yaw_sigma_rad_per_sqrt_m: random-walk heading noise.
        drift_rate_rad_s: heading drift rate while slowly slipping.
        drift_windows_s: (start, end) times of slow drift.
        hallucinated_turns: (time_s, yaw_rad, duration_s): the wheels report a turn that the
            robot did not make, spread over ``duration_s``.
    """

    scale_sigma: float = 0.01
    yaw_sigma_rad_per_sqrt_m: float = 0.004
    drift_rate_rad_s: float = 0.0
    drift_windows_s: tuple[tuple[float, float], ...] = ()
    hallucinated_turns: tuple[tuple[float, float, float], ...] = ()

    def __post_init__(self) -> None:
        if self.scale_sigma < 0 or self.yaw_sigma_rad_per_sqrt_m < 0:
            raise ConfigError("wheel noise sigmas must be >= 0")
        for start, end in self.drift_windows_s:
            if end < start:
                raise ConfigError(f"drift window ends before it starts: ({start}, {end})")
        for _, _, duration in self.hallucinated_turns:
            if duration <= 0:
                raise ConfigError(f"hallucinated turn duration must be > 0, got {duration}")


@dataclass(frozen=True)
class GpsFix:
    """A NavSatFix-like sample (no ROS types).

    Attributes:
        stamp_ns: time of the fix.
        latitude_deg, longitude_deg, altitude_m: geodetic position (NaN when no fix).
        east_m, north_m, up_m: the same in the local ENU frame about the datum.
        covariance_enu: 3×3 position covariance (m²), row-major tuple of 9.
        status: :data:`STATUS_FIX` or :data:`STATUS_NO_FIX`.
    """

    stamp_ns: int
    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    east_m: float
    north_m: float
    up_m: float
    covariance_enu: tuple[float, ...]
    status: int


@dataclass(frozen=True)
class LoopClosure:
    """A relative pose measurement between two frames where the path revisits itself.

    Attributes:
        from_index, to_index: frame indices (``from_index < to_index``).
        from_stamp_ns, to_stamp_ns: their stamps.
        delta: ``(dx_m, dy_m, dyaw_rad)`` of ``to`` in ``from``'s frame, with noise.
        covariance: 3×3 covariance of ``delta`` as a row-major tuple of 9.
    """

    from_index: int
    to_index: int
    from_stamp_ns: int
    to_stamp_ns: int
    delta: tuple[float, float, float]
    covariance: tuple[float, ...]


# ----------------------------------------------------------------------------- drives


@dataclass(frozen=True)
class DriveConfig:
    """A simulated drive.

    Attributes:
        name: label used in reports.
        seed: seeds the world, the object placement and every noise draw.
        segments: ``(duration_s, speed_m_s, yaw_rate_rad_s)`` pieces of the true path.
        frame_rate_hz: camera and wheel rate.
        slip: wheel error model.
        num_objects: near objects scattered beside the path.
        object_clearance_m: minimum distance from the path to an object's surface.
        object_spread_m: objects lie within this distance of the path.
        gps_period_s, gps_sigma_m, gps_dropout: GPS rate, noise and drop probability.
        loop_radius_m, loop_min_gap_s: revisits closer than the radius and at least the
            gap apart in time become loop closures (one per ``loop_min_gap_s``).
        width_px, height_px, fx_px: rendered camera (``fy = fx``, centred principal point).
        mounting: the stereo camera on the robot.
    """

    name: str = "drive"
    seed: int = 0
    segments: tuple[tuple[float, float, float], ...] = ((20.0, 1.3, 0.0),)
    frame_rate_hz: float = 10.0
    slip: WheelSlipConfig = field(default_factory=WheelSlipConfig)
    num_objects: int = 10
    object_clearance_m: float = 1.2
    object_spread_m: float = 8.0
    gps_period_s: float = 1.0
    gps_sigma_m: float = 1.5
    gps_dropout: float = 0.1
    loop_radius_m: float = 2.0
    loop_min_gap_s: float = 10.0
    width_px: int = 160
    height_px: int = 120
    fx_px: float = 125.0
    mounting: CameraMounting = field(
        default_factory=lambda: CameraMounting(pitch_rad=0.03, height_m=1.0, baseline_m=0.12)
    )

    def __post_init__(self) -> None:
        if not self.segments:
            raise ConfigError("a drive needs at least one segment")
        for duration, speed, _ in self.segments:
            if duration <= 0 or speed < 0:
                raise ConfigError(
                    f"segment duration must be > 0 and speed >= 0, got ({duration}, {speed})"
                )
        if self.frame_rate_hz <= 0:
            raise ConfigError(f"frame_rate_hz must be > 0, got {self.frame_rate_hz!r}")
        if not 0.0 <= self.gps_dropout <= 1.0:
            raise ConfigError(f"gps_dropout must be in [0, 1], got {self.gps_dropout!r}")


@dataclass
class Drive:
    """Everything recorded on one simulated drive (see :func:`make_drive`).

    Attributes:
        config: what was asked for.
        world: the scene (renders frames on demand).
        camera_info: the stereo camera.
        stamps_ns: ``(N,)`` frame stamps.
        truth: ``(N, 3)`` true poses ``(x_m, y_m, yaw_rad)`` of ``base_link``.
        wheel_deltas: ``(N, 3)`` wheel increments; row ``i`` is from frame ``i-1`` to ``i``
            (row 0 is zero).
        true_deltas: ``(N, 3)`` the true increments, same layout.
        gps: GPS samples, dropouts included (``status == STATUS_NO_FIX``).
        loop_closures: loop-closure measurements.
    """

    config: DriveConfig
    world: World
    camera_info: CameraInfo
    stamps_ns: NDArray[np.int64]
    truth: FloatArray
    wheel_deltas: FloatArray
    true_deltas: FloatArray
    gps: list[GpsFix]
    loop_closures: list[LoopClosure]

    def __len__(self) -> int:
        return len(self.stamps_ns)

    def frame(self, index: int) -> StereoFrame:
        """Render frame ``index``."""
        left, right = self.world.render_stereo(self.truth[index], index)
        return StereoFrame(left=left, right=right, stamp_ns=int(self.stamps_ns[index]))

    def frames(self) -> Iterator[StereoFrame]:
        """Render every frame in order."""
        for i in range(len(self)):
            yield self.frame(i)

    def wheel_poses(self) -> FloatArray:
        """``(N, 3)`` poses from integrating the wheel increments from the true start."""
        return integrate(self.truth[0], self.wheel_deltas[1:])


def _true_path(cfg: DriveConfig) -> tuple[FloatArray, FloatArray]:
    dt = 1.0 / cfg.frame_rate_hz
    speeds: list[float] = []
    rates: list[float] = []
    for duration, speed, rate in cfg.segments:
        n = max(1, int(round(duration * cfg.frame_rate_hz)))
        speeds += [speed] * n
        rates += [rate] * n
    v = np.array(speeds)
    w = np.array(rates)
    # Exact arc per step: travel along the chord at half the step's heading change.
    dyaw = w * dt
    chord = np.where(
        np.abs(dyaw) > 1e-9, 2.0 * v / np.where(w == 0, 1, w) * np.sin(dyaw / 2), v * dt
    )
    deltas = np.stack([chord * np.cos(dyaw / 2), chord * np.sin(dyaw / 2), dyaw], axis=-1)
    truth = integrate(np.zeros(3), deltas)
    return truth, np.vstack([np.zeros(3), deltas])


def _wheel(cfg: DriveConfig, true_deltas: FloatArray, rng: np.random.Generator) -> FloatArray:
    slip = cfg.slip
    dt = 1.0 / cfg.frame_rate_hz
    n = len(true_deltas)
    t = np.arange(n) * dt
    ds = np.hypot(true_deltas[:, 0], true_deltas[:, 1])
    ds_w = ds * (1.0 + slip.scale_sigma * rng.standard_normal(n))
    yaw_w = true_deltas[:, 2] + slip.yaw_sigma_rad_per_sqrt_m * np.sqrt(ds) * rng.standard_normal(
        n
    )
    for start, end in slip.drift_windows_s:
        yaw_w += np.where((t >= start) & (t < end), slip.drift_rate_rad_s * dt, 0.0)
    for when, yaw, duration in slip.hallucinated_turns:
        sel = (t >= when) & (t < when + duration)
        if np.any(sel):
            yaw_w[sel] += yaw / int(np.sum(sel))
    # Midpoint convention: the wheel odometer moves along half its own heading change.
    out = np.stack([ds_w * np.cos(yaw_w / 2), ds_w * np.sin(yaw_w / 2), yaw_w], axis=-1)
    out[0] = 0.0
    return out


def _place_objects(
    cfg: DriveConfig, truth: FloatArray, rng: np.random.Generator
) -> tuple[NearObject, ...]:
    objects: list[NearObject] = []
    tries = 0
    while len(objects) < cfg.num_objects and tries < 100 * (cfg.num_objects + 1):
        tries += 1
        anchor = truth[rng.integers(len(truth))]
        radius = float(rng.uniform(0.1, 0.5))
        ang = rng.uniform(-math.pi, math.pi)
        dist = rng.uniform(cfg.object_clearance_m + radius, cfg.object_spread_m)
        x = anchor[0] + dist * math.cos(ang)
        y = anchor[1] + dist * math.sin(ang)
        clearance = np.min(np.hypot(truth[:, 0] - x, truth[:, 1] - y)) - radius
        if clearance < cfg.object_clearance_m:
            continue
        objects.append(
            NearObject(x, y, radius, float(rng.uniform(1.5, 4.0)), float(rng.uniform()))
        )
    return tuple(objects)


def _gps(
    cfg: DriveConfig, truth: FloatArray, stamps_ns: NDArray[np.int64], rng: np.random.Generator
) -> list[GpsFix]:
    # Exact WGS-84, through the conversion the h2o_node uses: a spherical earth would put
    # fixes centimetres off (0.1 % of the distance), as much as an RTK receiver's noise.
    datum = Datum(*GPS_DATUM)
    step = max(1, int(round(cfg.gps_period_s * cfg.frame_rate_hz)))
    var = cfg.gps_sigma_m**2
    cov = (var, 0.0, 0.0, 0.0, var, 0.0, 0.0, 0.0, 4.0 * var)
    fixes: list[GpsFix] = []
    for i in range(0, len(truth), step):
        noise = rng.normal(0.0, cfg.gps_sigma_m, 3) * np.array([1.0, 1.0, 2.0])
        if rng.uniform() < cfg.gps_dropout:
            fixes.append(
                GpsFix(
                    int(stamps_ns[i]),
                    math.nan,
                    math.nan,
                    math.nan,
                    math.nan,
                    math.nan,
                    math.nan,
                    cov,
                    STATUS_NO_FIX,
                )
            )
            continue
        e = float(truth[i, 0] + noise[0])
        n_ = float(truth[i, 1] + noise[1])
        u = float(noise[2])
        lat, lon, alt = (float(v) for v in datum.to_geodetic(np.array([e, n_, u])))
        fixes.append(GpsFix(int(stamps_ns[i]), lat, lon, alt, e, n_, u, cov, STATUS_FIX))
    return fixes


def _loops(
    cfg: DriveConfig, truth: FloatArray, stamps_ns: NDArray[np.int64], rng: np.random.Generator
) -> list[LoopClosure]:
    gap = int(round(cfg.loop_min_gap_s * cfg.frame_rate_hz))
    sig = np.array([0.05, 0.05, 0.01])
    cov = tuple(float(v) for v in np.diag(sig**2).ravel())
    closures: list[LoopClosure] = []
    last = -gap
    for i in range(gap, len(truth)):
        if i - last < gap:
            continue
        dist = np.hypot(
            truth[: i - gap + 1, 0] - truth[i, 0], truth[: i - gap + 1, 1] - truth[i, 1]
        )
        if dist.size == 0 or dist.min() > cfg.loop_radius_m:
            continue
        j = int(np.argmin(dist))
        meas = planar_between(truth[j], truth[i]) + rng.normal(0.0, 1.0, 3) * sig
        closures.append(
            LoopClosure(
                j,
                i,
                int(stamps_ns[j]),
                int(stamps_ns[i]),
                (float(meas[0]), float(meas[1]), float(meas[2])),
                cov,
            )
        )
        last = i
    return closures


def make_drive(cfg: DriveConfig, world_config: WorldConfig | None = None) -> Drive:
    """Build a drive: true path, world with objects beside it, and all sensor records."""
    rng = np.random.default_rng(cfg.seed)
    truth, true_deltas = _true_path(cfg)
    stamps_ns = (np.arange(len(truth)) * (1e9 / cfg.frame_rate_hz)).astype(np.int64)
    wheel = _wheel(cfg, true_deltas, rng)
    objects = _place_objects(cfg, truth, rng)
    intr = CameraIntrinsics(
        cfg.width_px,
        cfg.height_px,
        cfg.fx_px,
        cfg.fx_px,
        (cfg.width_px - 1) / 2.0,
        (cfg.height_px - 1) / 2.0,
    )
    wcfg = world_config if world_config is not None else WorldConfig(seed=cfg.seed)
    world = World(wcfg, objects, intr, cfg.mounting)
    return Drive(
        config=cfg,
        world=world,
        camera_info=CameraInfo(intr, cfg.mounting),
        stamps_ns=stamps_ns,
        truth=truth,
        wheel_deltas=wheel,
        true_deltas=true_deltas,
        gps=_gps(cfg, truth, stamps_ns, rng),
        loop_closures=_loops(cfg, truth, stamps_ns, rng),
    )


def scenario(name: str, seed: int = 0, **overrides: object) -> DriveConfig:
    """Named drives used by tests and ``bench/vo.py``.

    * ``straight``: 30 s straight at 1.3 m/s, mild wheel noise.
    * ``loop``: a rounded square that returns to its start (two laps: loop closures).
    * ``slip``: the loop with heavy slip — slow drift and several hallucinated turns.
    * ``cluttered``: a gentle S-curve with many near objects beside the path.
    * ``sharp_turns``: street corners taken briskly — 90° left and right in 1 s (9° a frame),
      a 180° U-turn in 2 s and a 90° corner in 0.8 s (11° a frame), straights between.
    * ``spin``: turns on the spot (speed 0): a full turn at π/2 rad/s and a half turn at the
      thesis robot's top rate, π rad/s (18° a frame), between straights.

    ``overrides`` replace :class:`DriveConfig` fields (e.g. ``width_px=640``).
    """
    turn_rate = (math.pi / 2) / 3.0
    square = ((6.0, 1.3, 0.0), (3.0, 1.0, turn_rate)) * 4
    if name == "straight":
        cfg = DriveConfig(name=name, seed=seed, segments=((30.0, 1.3, 0.0),))
    elif name == "loop":
        cfg = DriveConfig(name=name, seed=seed, segments=square * 2, num_objects=12)
    elif name == "slip":
        slip = WheelSlipConfig(
            scale_sigma=0.02,
            yaw_sigma_rad_per_sqrt_m=0.01,
            drift_rate_rad_s=0.05,
            drift_windows_s=((4.0, 14.0), (40.0, 60.0)),
            hallucinated_turns=(
                (8.0, 0.4, 0.8),
                (22.0, -0.5, 1.0),
                (33.0, 0.35, 0.6),
                (50.0, -0.45, 0.9),
                (64.0, 0.3, 0.5),
            ),
        )
        cfg = DriveConfig(name=name, seed=seed, segments=square * 2, slip=slip, num_objects=12)
    elif name == "cluttered":
        cfg = DriveConfig(
            name=name,
            seed=seed,
            segments=((8.0, 1.3, 0.0), (6.0, 1.2, 0.15), (6.0, 1.2, -0.15), (8.0, 1.3, 0.0)),
            num_objects=60,
            object_clearance_m=0.8,
            object_spread_m=6.0,
            slip=WheelSlipConfig(
                drift_rate_rad_s=0.03,
                drift_windows_s=((0.0, 28.0),),
                hallucinated_turns=((12.0, 0.3, 0.5),),
            ),
        )
    elif name == "sharp_turns":
        right_angle = math.pi / 2
        cfg = DriveConfig(
            name=name,
            seed=seed,
            segments=(
                (5.0, 1.3, 0.0),
                (1.0, 1.0, right_angle),
                (5.0, 1.3, 0.0),
                (1.0, 1.0, -right_angle),
                (4.0, 1.3, 0.0),
                (2.0, 0.8, math.pi / 2.0),
                (5.0, 1.3, 0.0),
                (0.8, 0.8, right_angle / 0.8),
                (5.0, 1.3, 0.0),
            ),
            num_objects=12,
        )
    elif name == "spin":
        cfg = DriveConfig(
            name=name,
            seed=seed,
            segments=(
                (4.0, 1.3, 0.0),
                (4.0, 0.0, math.pi / 2.0),
                (4.0, 1.3, 0.0),
                (1.0, 0.0, -math.pi),
                (4.0, 1.3, 0.0),
            ),
            num_objects=12,
        )
    else:
        raise ConfigError(
            f"unknown scenario {name!r}; choose straight, loop, slip, cluttered, sharp_turns "
            "or spin"
        )
    if overrides:
        from dataclasses import replace

        cfg = replace(cfg, **overrides)  # type: ignore[arg-type]
    return cfg
