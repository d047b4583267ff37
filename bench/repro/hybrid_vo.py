"""Thesis Table 2.1: hybrid VO against full VO, cost per frame and accuracy.

The thesis (§2.5) times its hybrid odometer and the full 6-DOF VO of Agrawal et al. on the
same logs (Table 2.1) and shows their trajectories (Figs. 2.4, 2.5) as "comparable". We run
``bench/vo.py``'s drives (rendered at 640×480) and ``bench/vo_kitti.py``'s KITTI clip with
the hybrid odometer, a full stereo VO of the VISO2-S kind (``vo_full.CircularStereoVO``)
and the earlier KLT full VO (``vo_full.FullStereoVO``) on the same frames.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import vo
import vo_kitti

from repro.context import Context, verdict

TITLE = "Thesis Table 2.1 — hybrid VO against full VO (bench/repro/hybrid_vo.py)"

#: Table 2.1: (log, full VO ms, hybrid VO + range ms, hybrid VO ms) on a 2 GHz Pentium 4M.
SEED_TABLE = (
    ("Field Loop", 266.0, 11.5, 8.0),
    ("Building Lap", 238.0, 11.0, 8.2),
    ("Forest Path", 153.0, 14.0, 9.3),
)
#: VISO2-S's translation error on the KITTI odometry benchmark (segments of 100–800 m).
VISO2S_DRIFT_PCT = 2.4

QUICK_DRIVES = ("sharp_turns", "spin")
FULL_DRIVES = ("straight", "loop", "slip", "cluttered", "sharp_turns", "spin")
WIDTH_PX = 640

#: Plot order and style: (key, label, colour).
CURVES = (
    ("wheel", "wheels only", "tab:gray"),
    ("hybrid", "hybrid VO", "tab:blue"),
    ("full", "full VO (VISO2-S kind)", "tab:red"),
    ("klt", "full VO (earlier KLT)", "tab:orange"),
)


def kitti_folder(ctx: Context) -> Path | None:
    """The KITTI clip ``bench/reproduce.py --kitti DIR`` names, when it holds ``poses.txt``."""
    return ctx.kitti if ctx.kitti is not None and (ctx.kitti / "poses.txt").exists() else None


def plot(path: Path, title: str, poses: dict[str, np.ndarray], truth: np.ndarray) -> None:
    """Left: trajectories in the plane, ground truth dashed and drawn on top. Right: position
    error per frame (the curves overlap at the left panel's scale; frames, not distance, so
    turns on the spot show). Legend outside the data."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames = np.arange(len(truth))
    fig, (ax, err) = plt.subplots(1, 2, figsize=(11.0, 4.6),
                                  gridspec_kw={"width_ratios": [1.25, 1.0]})
    for key, label, colour in CURVES:
        if key in poses:
            xy = poses[key]
            ax.plot(xy[:, 0], xy[:, 1], color=colour, lw=1.3, label=label, zorder=2)
            err.plot(frames, np.hypot(*(xy[:, :2] - truth[:, :2]).T), color=colour, lw=1.3)
    ax.plot(truth[:, 0], truth[:, 1], color="black", ls="--", lw=1.6, label="ground truth",
            zorder=10)
    ax.plot(truth[0, 0], truth[0, 1], "ko", ms=5, zorder=11, label="start")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, alpha=0.3)
    err.set_xlabel("frame")
    err.set_ylabel("position error (m)")
    err.grid(True, alpha=0.3)
    fig.suptitle(title, fontsize=10)
    fig.legend(*ax.get_legend_handles_labels(), loc="center left", bbox_to_anchor=(0.80, 0.5),
               fontsize=8, frameon=False)
    fig.tight_layout(rect=(0.0, 0.0, 0.79, 1.0))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _reasons(reasons: object) -> str:
    """The hybrid's fallback reasons beyond the first frame, as ``(reason n, …)``."""
    assert isinstance(reasons, dict)
    rest = {k: v for k, v in reasons.items() if k != "first_frame"}
    return "(" + ", ".join(f"{k} {v}" for k, v in rest.items()) + ")" if rest else ""


def _four(values: dict[str, float], fmt: str = "{:.3g}") -> str:
    return " / ".join(fmt.format(values[k]) for k in ("wheel", "hybrid", "full", "klt"))


def run(ctx: Context) -> str:
    """Run the drives and the KITTI clip; the section's markdown."""
    drives = QUICK_DRIVES if ctx.quick else FULL_DRIVES
    rows = [vo.run_drive(name, 0, WIDTH_PX) for name in drives]
    folder = kitti_folder(ctx)
    kitti = vo_kitti.run_kitti(folder) if folder is not None else None

    out = [
        "Seed: thesis §2.5, Table 2.1 (CPU ms per frame on a 2 GHz Pentium 4M, 160×120 "
        "images for the hybrid, the full VO of Agrawal et al. [1] on the same logs) and "
        "Figs. 2.4–2.5 (accuracy: \"full VO and hybrid VO perform comparably\", no table).",
        "",
        "### Cost per frame",
        "",
        "| run | full VO ms | hybrid VO + range ms | hybrid VO ms | hybrid (+ range) / full |",
        "| --- | --- | --- | --- | --- |",
    ]
    for log, full_ms, ranged_ms, bare_ms in SEED_TABLE:
        out.append(f"| thesis: {log} | {full_ms:.0f} | {ranged_ms:.1f} | {bare_ms:.1f} | "
                   f"{100 * ranged_ms / full_ms:.1f}% |")
    ratios = []
    for r in rows:
        ratio = float(r["hybrid_ms"]) / float(r["full_ms"])  # type: ignore[arg-type]
        ratios.append(ratio)
        out.append(f"| ours: {r['name']} (640×480) | {r['full_ms']:.1f} | "
                   f"{r['hybrid_ms']:.2f} | — | {100 * ratio:.1f}% |")
    if kitti is not None:
        ratio = kitti.hybrid_ms / kitti.full_ms
        ratios.append(ratio)
        out.append(f"| ours: KITTI clip (1226×370) | {kitti.full_ms:.1f} | "
                   f"{kitti.hybrid_ms:.2f} | — | {100 * ratio:.1f}% |")
    out += [
        "",
        "Ours always ranges its patches on the stereo pair (per-patch stereo, as the thesis' "
        "\"+ range\" column), so its cost belongs in that column. The earlier KLT full VO "
        "costs " + ", ".join(f"{r['name']} {r['klt_ms']:.0f} ms" for r in rows)
        + (f", KITTI {kitti.klt_ms:.0f} ms" if kitti is not None else "") + ".",
        "",
        "### Accuracy",
        "",
        "Drift = KITTI's translation error (the benchmark's protocol on shorter segments: "
        f"{', '.join(f'{v:g}' for v in vo.SEGMENTS_M)} m on the drives, "
        f"{', '.join(f'{v:g}' for v in vo_kitti.KITTI_SEGMENTS_M)} m on the clip; KITTI "
        "ranks on 100–800 m). A full VO that fails on a frame takes the wheel increment; "
        "\"failed\" counts those frames.",
        "",
        "| run | length m | sharpest turn °/frame | drift % wheel / hybrid / full / KLT | "
        "heading RMSE ° wheel / hybrid / full / KLT | ATE m wheel / hybrid / full / KLT | "
        "failed full / KLT | hybrid deferred |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        m = r["metrics"]
        assert isinstance(m, dict)
        drift = {k: m[k]["drift_pct"] for k in m}
        heading = {k: math.degrees(m[k]["heading_rmse_rad"]) for k in m}
        ate = {k: m[k]["ate_m"] for k in m}
        out.append(
            f"| {r['name']} | {r['length_m']:.1f} | {r['max_turn_deg_per_frame']:.0f} | "
            f"{_four(drift, '{:.2f}')} | {_four(heading, '{:.2f}')} | {_four(ate)} | "
            f"{100 * float(r['full_failed']):.1f}% / "  # type: ignore[arg-type]
            f"{100 * float(r['klt_failed']):.1f}% | "  # type: ignore[arg-type]
            f"{100 * float(r['deferred']):.1f}% {_reasons(r['reasons'])} |"  # type: ignore[arg-type]
        )
    if kitti is not None:
        final_yaw = {k: math.degrees(v) for k, v in kitti.final_yaw_err_rad.items()}
        out.append(
            f"| KITTI clip | {kitti.length_m:.1f} | "
            f"{math.degrees(float(np.max(np.abs(np.diff(kitti.poses['truth'][:, 2]))))):.1f} | "
            f"{_four(kitti.drift_pct, '{:.2f}')} | final {_four(final_yaw, '{:.2f}')} | "
            f"final pos err {_four(kitti.final_pos_err_m)} | — | "
            f"{100 * kitti.deferred:.1f}% |"
        )
    else:
        out.append("| KITTI clip | not given (`--kitti DIR`) or without `poses.txt` "
                   "| | | | | | |")

    # Figures.
    out += ["", "### Trajectories", ""]
    for r in rows:
        png = ctx.plots / f"vo_{r['name']}.png"
        poses = r["poses"]
        truth = r["truth"]
        assert isinstance(poses, dict) and isinstance(truth, np.ndarray)
        plot(png, f"{r['name']}: {r['length_m']:.0f} m, sharpest turn "
             f"{r['max_turn_deg_per_frame']:.0f}°/frame", poses, truth)
        out.append(ctx.link(png))
    if kitti is not None:
        png = ctx.plots / "vo_kitti.png"
        poses = {k: v for k, v in kitti.poses.items() if k != "truth"}
        plot(png, f"KITTI clip: {kitti.length_m:.0f} m (wheels: truth + yaw noise)", poses,
             kitti.poses["truth"])
        out.append(ctx.link(png))

    # Where the baseline stands and how the protocol differs.
    full_drift = {str(r["name"]): r["metrics"]["full"]["drift_pct"] for r in rows}  # type: ignore[index]
    klt_drift = {str(r["name"]): r["metrics"]["klt"]["drift_pct"] for r in rows}  # type: ignore[index]
    turns = [n for n in ("sharp_turns", "spin") if n in full_drift]
    max_heading_deg = (math.degrees(float(np.max(np.abs(kitti.poses["truth"][:, 2]))))
                       if kitti is not None else math.nan)
    out += [
        "",
        "### The full-VO baseline",
        "",
        f"VISO2-S reaches about {VISO2S_DRIFT_PCT} % translation drift on KITTI's benchmark. "
        "Ours, of the same kind (grid-spread ORB corners, circular matching previous left → "
        "previous right → current right → current left → previous left, KLT sub-pixel "
        "refinement, bucketing, PnP RANSAC, Gauss–Newton on the reprojection error in both "
        "current images): "
        + (f"{kitti.drift_pct['full']:.2f} % on the KITTI clip (KLT baseline "
           f"{kitti.drift_pct['klt']:.2f} %), " if kitti is not None else "")
        + "; ".join(f"{n} {full_drift[n]:.2f} % (KLT {klt_drift[n]:.2f} %)" for n in turns)
        + ". The KITTI clip is nearly straight (its heading never moves more than "
        + (f"{max_heading_deg:.1f}° from the start" if kitti is not None else "a degree or two")
        + "), so it cannot show a full VO drifting through a sharp turn; the synthetic "
        "`sharp_turns` (90° corners in 1 s and 0.8 s, a U-turn in 2 s) and `spin` (on-the-spot "
        "turns at up to π rad/s, 18°/frame, the thesis robot's top rate) drives are the turn "
        "test. Frames the full VOs failed on (took the wheels' increment): "
        + "; ".join(f"{r['name']} {100 * float(r['full_failed']):.1f} % VISO2-S kind, "  # type: ignore[arg-type]
                    f"{100 * float(r['klt_failed']):.1f} % KLT" for r in rows)  # type: ignore[arg-type]
        + ". The KLT baseline's pyramidal search has no motion prior; the circular matcher "
        "searches 200 px around where the last frame's rotation predicts each corner.",
        "",
        "Protocol differences:",
        "",
        "- Platform: one core of this machine (shared, timings indicative), Python + OpenCV "
        "for both odometers, against a 2 GHz Pentium 4M running compiled Lush + IPP (hybrid) "
        "and Agrawal et al.'s C++ VO with bundle adjustment (full). Only the ratio compares.",
        "- Data: synthetic drives rendered by `hybrid_vo.sim.world` (far textured scenery, "
        "textured ground, posts; 640×480, 0.12 m baseline, 10 Hz) and a 51-frame KITTI clip, "
        "against the thesis' 200 m outdoor logs with GPS as reference. Our ground truth is "
        "exact; KITTI has no wheels, so its wheel input is the true travel plus yaw noise.",
        "- The thesis' full VO adds bundle adjustment; ours is frame-to-frame (as VISO2-S). "
        "Our hybrid's ranging is always on, so we have no bare \"hybrid VO\" column.",
        "- Accuracy: the thesis shows trajectories against GPS (Figs. 2.4, 2.5) and no "
        "accuracy table; we report drift, heading RMSE and ATE against ground truth.",
        "",
    ]
    heading = {str(r["name"]): (r["metrics"]["full"]["heading_rmse_rad"],  # type: ignore[index]
                                r["metrics"]["klt"]["heading_rmse_rad"])  # type: ignore[index]
               for r in rows}
    worse = [n for n, (f, k) in heading.items() if f > k]
    if worse:
        bias = []
        for r in rows:
            if r["name"] in worse:
                est, truth = r["poses"]["full"], r["truth"]  # type: ignore[index]
                end = math.degrees(float(np.angle(np.exp(1j * (est[-1, 2] - truth[-1, 2])))))
                bias.append(f"{r['name']} {1e3 * end / (len(truth) - 1):+.1f}")
        out.insert(out.index("Protocol differences:") - 1,
                   "\nThe new baseline is not better everywhere: its heading RMSE exceeds the "
                   f"KLT one's on {', '.join(worse)} (of {len(heading)} drives). Its final "
                   "heading error divided by the frames (millidegrees a frame): "
                   f"{', '.join(bias)} — a small steady yaw bias. Likely cause: the noisy "
                   "depth of far points (disparity below 1 px) leaking into yaw through the "
                   "parallax of the forward motion; in a side run, `min_disparity_px=1` "
                   "removed the bias on `straight` but doubled the per-frame yaw noise in "
                   "`sharp_turns`' turns, so the default keeps them.")
    worst = max(ratios)
    hybrid_vs_full = [
        r["metrics"]["hybrid"]["ate_m"] / max(r["metrics"]["full"]["ate_m"], 1e-12)  # type: ignore[index]
        for r in rows
    ]
    seed_low = min(s[2] / s[1] for s in SEED_TABLE)
    seed_high = max(s[2] / s[1] for s in SEED_TABLE)
    names = [str(r["name"]) for r in rows]
    worst_ate = names[int(np.argmax(hybrid_vs_full))]
    word = "reproduced" if worst <= 0.1 and max(hybrid_vs_full) <= 1.5 else (
        "reproduced in shape" if worst <= 0.2 else "not reproduced")
    out.append(verdict(
        word,
        f"hybrid VO costs {100 * min(ratios):.1f}–{100 * worst:.1f} % of a VISO2-S-kind full "
        f"VO per frame (thesis: {100 * seed_low:.1f}–{100 * seed_high:.1f} % with ranging), "
        f"and its ATE is {min(hybrid_vs_full):.2f}–{max(hybrid_vs_full):.2f}× the full VO's "
        f"on the synthetic drives (\"comparable\" in the thesis; the worst is {worst_ate}"
        + (", where 60 near posts give the full VO better translation than the wheels the "
           "hybrid keeps" if worst_ate == "cluttered" else "")
        + ") — on synthetic scenes with exact ground truth"
        + (" and a 51-frame, nearly straight KITTI clip" if kitti is not None else
           " (the KITTI clip was not found)")
        + ", not on the thesis' outdoor logs."))
    return "\n".join(out) + "\n"
