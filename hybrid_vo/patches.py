"""Per-patch steps of thesis §2.3: sampling, range test (2.3), NCC search, vote, σ, (2.4).

Everything here is a pure function on numpy arrays; :mod:`hybrid_vo.odometer` strings them
together. Spherical-image conventions are those of :mod:`hybrid_vo.camera` (θ grows to the
right, one column = ``a`` radians).
"""

from __future__ import annotations

import math
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
Float32Array = NDArray[np.float32]


def r_min_m(d_m: float, theta_rad: float, theta_p_rad: float) -> float:
    """Eq. (2.3): the nearest range at which forward travel ``d_m`` shifts bearing θ < θ_p/2.

    ``r_min = d tan(θ_p/2 + θ) / (cos θ tan(θ_p/2 + θ) − sin θ)``. θ is taken in absolute
    value (the geometry is symmetric); ``d_m`` is the largest travel between two frames.
    """
    theta = abs(theta_rad)
    tan_t = math.tan(theta_p_rad / 2.0 + theta)
    return d_m * tan_t / (math.cos(theta) * tan_t - math.sin(theta))


def bearing_shift_rad(range_m: float, theta_rad: float, d_m: float) -> float:
    """Change of bearing of a point at ``range_m`` and bearing θ after moving ``d_m`` forward.

    The construction of Fig. 2.2, used to check (2.3): the point is at
    ``(r cos θ, r sin θ)``; after moving forward it is at ``(r cos θ − d, r sin θ)``.
    """
    theta = abs(theta_rad)
    return math.atan2(range_m * math.sin(theta), range_m * math.cos(theta) - d_m) - theta


def parallax_rad(range_m: float, theta_rad: float, dx_m: float, dy_m: float) -> float:
    """Column-direction shift (rad, θ to the right) of a point seen from a translating camera.

    The point lies ``range_m`` away (horizontally) at bearing θ (to the right of the base
    x axis); the camera moves by ``(dx_m, dy_m)`` (base frame, y to the left) without
    turning. A positive result moves the point to the right in the spherical image, as a
    left turn would. The 2-D generalisation of Fig. 2.2 (:func:`bearing_shift_rad` is the
    forward-only case): the parallax (2.3) bounds by ``θ_p/2`` at ``r_min``, which a
    sub-pixel NCC peak still measures and the odometer therefore subtracts. ``inf`` range
    gives 0.
    """
    if not math.isfinite(range_m):
        return 0.0
    # REP-103 bearing ψ = −θ; the point's new bearing from the moved camera is ψ'.
    px, py = range_m * math.cos(theta_rad), -range_m * math.sin(theta_rad)
    psi_new = math.atan2(py - dy_m, px - dx_m)
    shift = -theta_rad - psi_new
    return (shift + math.pi) % (2.0 * math.pi) - math.pi


def sample_patches(
    image: Float32Array,
    col_lo: int,
    col_hi: int,
    num_patches: int,
    patch_w: int,
    patch_h: int,
    min_response: float,
) -> list[tuple[int, int]]:
    """Patch centres ``(row, col)`` at the strongest Harris corners in columns [lo, hi).

    The region is shrunk by half a patch on all sides so patches lie wholly inside it; after
    each pick the corners under that patch are zeroed (the thesis's non-max suppression).
    ``min_response`` is relative to the image's intensity variance, so a blank view yields
    no patches at all.
    """
    rows, cols = image.shape
    hw, hh = patch_w // 2, patch_h // 2
    lo = max(col_lo, hw)
    hi = min(col_hi, cols - hw)
    if hi <= lo or rows < patch_h:
        return []
    # Harris on a margin-padded strip so the derivative kernels see real pixels.
    a0 = max(0, lo - 3)
    b0 = min(cols, hi + 3)
    strip = np.ascontiguousarray(image[:, a0:b0])
    resp = cv2.cornerHarris(strip, 3, 3, 0.04)
    resp = resp[:, lo - a0 : hi - a0].copy()
    resp[:hh, :] = 0.0
    resp[rows - hh :, :] = 0.0
    # Harris response scales with intensity^4; normalise so the threshold is contrast-free.
    # cv2's mean/std is ~10x cheaper than np.var on a strip this size (per frame, it shows).
    std = float(cv2.meanStdDev(strip)[1][0, 0])
    scale = (std * std) ** 2 + 1e-6
    picks: list[tuple[int, int]] = []
    for _ in range(num_patches):
        idx = int(resp.argmax())
        r, c = divmod(idx, resp.shape[1])
        if resp[r, c] / scale <= min_response:
            break
        picks.append((r, c + lo))
        resp[max(0, r - hh) : r + hh + 1, max(0, c - hw) : c + hw + 1] = 0.0
    return picks


def alternate_sides(picks: list[tuple[int, int]], split_col: float) -> list[tuple[int, int]]:
    """Patch centres reordered to alternate between the two sides of column ``split_col``.

    ``picks`` come strongest first; the order within each side is kept and the strongest
    pick leads. Forward travel shifts far features outward on both sides of the direction
    of travel by ``d·sin θ / r``; taking the first N of this order keeps the sides in
    balance so that the parallax of features too far for stereo to range cancels in the
    mean instead of adding up over a drive.
    """
    left = [p for p in picks if p[1] < split_col]
    right = [p for p in picks if p[1] >= split_col]
    first, second = (left, right) if left and (not right or picks[0] == left[0]) else (right, left)
    out: list[tuple[int, int]] = []
    for i in range(max(len(first), len(second))):
        out += first[i : i + 1] + second[i : i + 1]
    return out


def parabola_offset(left: float, mid: float, right: float) -> float:
    """Sub-pixel offset in [-0.5, 0.5] of the vertex of a parabola through three samples."""
    denom = left - 2.0 * mid + right
    if denom >= 0.0:
        return 0.0
    # Plain min/max: np.clip on a scalar costs more than the rest of this per-patch step.
    return max(-0.5, min(0.5, 0.5 * (left - right) / denom))


def peak_sigma_px(left: float, mid: float, right: float) -> float:
    """σ (pixels) of a normal fitted to an NCC peak by matching second derivatives (§2.3.5).

    For ``g = A exp(−x²/2σ²)``, ``g''(0) = −A/σ²``; with the numerical second derivative
    ``c'' = left − 2·mid + right`` and ``A = mid``: ``σ = sqrt(−mid / c'')``. A flat or
    inverted peak gives ``inf``.
    """
    curv = left - 2.0 * mid + right
    if curv >= 0.0 or mid <= 0.0:
        return math.inf
    return math.sqrt(-mid / curv)


def ncc_search(
    template: Float32Array, window: Float32Array
) -> tuple[float, float, float, float] | None:
    """Best match of ``template`` in ``window`` by normalized cross-correlation.

    Returns ``(row, col, peak_ncc, sigma_col_px)`` of the template's top-left corner in the
    window with sub-pixel refinement along columns and rows, or None when the peak sits on
    the window's left/right edge (the true match may lie outside) or the window is flat.
    """
    if window.shape[0] < template.shape[0] or window.shape[1] < template.shape[1]:
        return None
    res = cv2.matchTemplate(window, template, cv2.TM_CCOEFF_NORMED)
    # One reduction instead of a per-pixel test: a NaN or inf anywhere makes the sum one.
    if not math.isfinite(float(res.sum())):
        res = np.nan_to_num(res, nan=-1.0, posinf=-1.0, neginf=-1.0)
    r, c = divmod(int(res.argmax()), res.shape[1])
    if res.shape[1] < 3 or c == 0 or c == res.shape[1] - 1:
        return None
    peak = float(res[r, c])
    lft, rgt = float(res[r, c - 1]), float(res[r, c + 1])
    dc = parabola_offset(lft, peak, rgt)
    dr = 0.0
    if 0 < r < res.shape[0] - 1:
        dr = parabola_offset(float(res[r - 1, c]), peak, float(res[r + 1, c]))
    return r + dr, c + dc, peak, peak_sigma_px(lft, peak, rgt)


def track_patch(
    prev: Float32Array,
    cur: Float32Array,
    row: int,
    col: int,
    patch_w: int,
    patch_h: int,
    col_lo: int,
    col_hi: int,
    symmetric: bool = True,
    max_asymmetry_px: float = 1.0,
) -> tuple[float, float, float] | None:
    """Column shift (px) of the patch centred at ``(row, col)`` of ``prev`` into ``cur``.

    The search window spans columns ``[col_lo, col_hi)`` and half a patch above and below.
    Returns ``(shift_px, peak_ncc, sigma_px)`` of the forward match, or None when no
    interior peak exists.

    ``symmetric``: the parabola through an NCC peak is not centred on the true shift when the
    peak is lopsided, which it is for most textures: identical images give a non-zero
    shift, the same for the same feature in frame after frame, i.e. a heading drift. The
    patch found in ``cur`` is therefore matched back into ``prev`` and the two shifts are
    averaged, ``(s_fwd − s_bwd)/2``: a true shift flips sign between the two directions
    while the texture's lopsidedness does not, so it cancels. A back match that fails or
    disagrees with the forward one by more than ``max_asymmetry_px`` rejects the patch.
    """
    rows, cols = cur.shape
    hw, hh = patch_w // 2, patch_h // 2
    tmpl = prev[row - hh : row + hh + 1, col - hw : col + hw + 1]
    r0, r1 = max(row - 2 * hh, 0), min(row + 2 * hh + 1, rows)
    c0, c1 = max(col_lo, 0), min(col_hi, cols)
    found = ncc_search(tmpl, cur[r0:r1, c0:c1])
    if found is None:
        return None
    f_row, f_col, peak, sigma_px = found
    fwd = c0 + f_col + hw - col
    if not symmetric:
        return fwd, peak, sigma_px
    rc = int(round(r0 + f_row + hh))
    cc = int(round(c0 + f_col + hw))
    if rc - hh < 0 or rc + hh >= rows or cc - hw < 0 or cc + hw >= cols:
        return None
    back = cur[rc - hh : rc + hh + 1, cc - hw : cc + hw + 1]
    # Two columns either side of where the forward match says the patch came from.
    guess = int(round(cc - fwd))
    b0, b1 = max(guess - hw - 2, 0), min(guess + hw + 3, cols)
    rb0, rb1 = max(rc - 2 * hh, 0), min(rc + 2 * hh + 1, rows)
    found_b = ncc_search(back, prev[rb0:rb1, b0:b1])
    if found_b is None:
        return None
    bwd = b0 + found_b[1] + hw - cc
    if abs(fwd + bwd) > max_asymmetry_px:
        return None
    return 0.5 * (fwd - bwd), peak, sigma_px


def stereo_range_m(
    left: Float32Array | NDArray[np.uint8],
    right: Float32Array | NDArray[np.uint8],
    u_px: float,
    v_px: float,
    fx_px: float,
    baseline_m: float,
    max_disparity_px: int,
    half_w: int,
    half_h: int,
    min_ncc: float,
) -> float:
    """Depth (m, along the optical axis) of the point at ``(u, v)`` from per-patch stereo.

    Matches a ``(2·half_h+1) × (2·half_w+1)`` template around ``(u, v)`` in the left image
    along the same row of the right image (rectified pair) for disparities
    ``0..max_disparity_px`` (the approach of [1] the thesis cites for when no dense stereo is
    at hand). Returns ``inf`` for zero disparity and NaN when the match is unreliable (low
    NCC, template out of the image, peak at the largest disparity searched).
    """
    rows, cols = left.shape
    ui, vi = int(round(u_px)), int(round(v_px))
    if vi - half_h < 0 or vi + half_h >= rows or ui - half_w < 0 or ui + half_w >= cols:
        return math.nan
    tmpl = left[vi - half_h : vi + half_h + 1, ui - half_w : ui + half_w + 1]
    lo = max(0, ui - half_w - max_disparity_px)
    strip = right[vi - half_h : vi + half_h + 1, lo : ui + half_w + 1]
    res = cv2.matchTemplate(strip, tmpl, cv2.TM_CCOEFF_NORMED)[0]
    if not math.isfinite(float(res.sum())):
        return math.nan
    c = int(res.argmax())
    if res[c] < min_ncc:
        return math.nan
    disparity = float((ui - half_w) - (lo + c))
    if lo > 0 and c == 0:
        return math.nan  # nearer than the disparity range can see
    if 0 < c < len(res) - 1:
        disparity -= parabola_offset(float(res[c - 1]), float(res[c]), float(res[c + 1]))
    if disparity <= 0.25:
        return math.inf
    return fx_px * baseline_m / disparity


def vote(estimates_rad: FloatArray, theta_p_rad: float) -> NDArray[np.bool_]:
    """Cross-validation vote (§2.3.4): the inlier mask of the patches' yaw estimates.

    Each patch votes for every *other* patch whose estimate differs by less than θ_p; a
    patch whose tally is more than half the number of patches is an inlier.
    """
    est = np.asarray(estimates_rad, dtype=float)
    n = est.size
    close = np.abs(est[:, None] - est[None, :]) < theta_p_rad
    np.fill_diagonal(close, False)
    tally = close.sum(axis=1)
    result: NDArray[np.bool_] = tally > n / 2.0
    return result


def balance_weights(weights: FloatArray, left: NDArray[np.bool_]) -> FloatArray:
    """Weights rescaled so both sides of the direction of travel weigh the same in total.

    With patches on both sides, an outward parallax common to them cancels in the weighted
    mean; with one side empty the weights are returned unchanged.
    """
    w = np.asarray(weights, dtype=float).copy()
    wl, wr = float(np.sum(w[left])), float(np.sum(w[~left]))
    if wl > 0.0 and wr > 0.0:
        w[left] *= 0.5 / wl
        w[~left] *= 0.5 / wr
    return w


def merge_sigmas(
    sigmas_rad: FloatArray, rule: Literal["thesis", "inverse_variance"] = "thesis"
) -> float:
    """Merge per-patch yaw σ into the σ of the bearing estimate.

    ``thesis``: ``σ_θ = (Σ σ_i⁻¹)⁻¹`` exactly as printed in §2.3.5 (for N equal σ it gives
    σ/N). ``inverse_variance``: ``σ_θ = (Σ σ_i⁻²)^(−1/2)``, the usual combination of
    independent estimates (σ/√N for N equal σ).
    """
    s = np.asarray(sigmas_rad, dtype=float)
    if s.size == 0 or np.any(~(s > 0)):
        raise ValueError(f"sigmas must be a non-empty array of positive values, got {s!r}")
    if rule == "thesis":
        return float(1.0 / np.sum(1.0 / s))
    if rule == "inverse_variance":
        return float(1.0 / math.sqrt(float(np.sum(1.0 / s**2))))
    raise ValueError(f"unknown sigma merge rule {rule!r}; choose 'thesis' or 'inverse_variance'")


def localize(
    p_xy: FloatArray, theta_v_rad: float, theta_w_rad: float, dp_w_xy: FloatArray
) -> FloatArray:
    """Eq. (2.4): ``p' = p + R(θ_v/2) R(−θ_w) Δp_w`` (midpoint rule), all planar, ``(2,)``.

    ``Δp_w`` is the wheel translation in the frame of ``p`` in which the wheel odometer's
    rotation θ_w has been applied in full (its end-of-step heading); (2.4) undoes θ_w and
    applies half the visual rotation θ_v instead.
    """
    a = theta_v_rad / 2.0 - theta_w_rad
    c, s = math.cos(a), math.sin(a)
    dp = np.asarray(dp_w_xy, dtype=float)
    return np.asarray(p_xy, dtype=float) + np.array([c * dp[0] - s * dp[1], s * dp[0] + c * dp[1]])
