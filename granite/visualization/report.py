"""Plots (PNG, matplotlib's Agg canvas: headless, no display, no pyplot state) and the
``report.md`` of a run folder. Each ``plot_*`` function saves its PNG and returns the figure.

Files (each written atomically; a plot that has no data is not written and the report says why):

======================  =========================================================================
``trajectory.png``      top view (x, y) and height (z) over time of the estimate, Sim(3)-aligned
                        to the ground truth per sub-map (each sub-map its own colour), and the
                        ground truth; needs ground truth
``translation_error.png``  position error of every aligned pose (ATE) and the RPE translation
                        error over Δ (paper Eq. 18-20), over time; needs ground truth
``points.png``          tracked points, connected finite and infinite landmarks per frame, with
                        keyframes, skipped frames, restarts and re-initialisations marked
``scale.png``           relative scale error (estimated / true length of the last Δ of motion in
                        the sub-map's aligned scale, minus 1; :mod:`granite.evaluation.scale_drift`),
                        and the scale-drift indicator Λ when ``diagnostics.csv`` has a
                        ``scale_drift_indicator`` column; needs ground truth
``report.md``           the metrics, the configuration and the plots
======================  =========================================================================

Time axes are seconds since the first frame of the run.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from granite.errors import GraniteError
from granite.estimator.diagnostics import FrameDiagnostics
from granite.evaluation import ate, relative_scale_error, rpe
from granite.io import atomic_write_bytes, atomic_write_text
from granite.trajectory import Trajectory

#: Every file this module may write (stale ones from an earlier run are removed).
PLOT_FILES = ("trajectory.png", "translation_error.png", "points.png", "scale.png")
REPORT_FILE = "report.md"
#: Diagnostics column of the scale-drift indicator Λ (paper Eq. 17), plotted once it exists.
LAMBDA_COLUMN = "scale_drift_indicator"

GT_COLOR = "#2ca02c"
SUBMAP_COLORS = ("#d62728", "#1f77b4", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22")
DPI = 110


@dataclass
class Report:
    """What :func:`write_report` wrote: plot file names and why the others are missing."""

    plots: dict[str, str] = field(default_factory=dict)  # file name -> caption
    missing: dict[str, str] = field(default_factory=dict)  # file name -> reason
    path: Path | None = None


def _color(submap: int) -> str:
    return SUBMAP_COLORS[int(submap) % len(SUBMAP_COLORS)]


def _save(fig: Figure, path: Path) -> None:
    FigureCanvasAgg(fig)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=DPI)
    atomic_write_bytes(path, buffer.getvalue())


def _blocks(ids: np.ndarray) -> list[tuple[int, int]]:
    """``[start, stop)`` of runs of equal values."""
    if len(ids) == 0:
        return []
    cuts = np.flatnonzero(np.diff(ids) != 0) + 1
    bounds = [0, *cuts.tolist(), len(ids)]
    return list(zip(bounds[:-1], bounds[1:]))


def _submap_label(sid: int, scale: float | None) -> str:
    return f"estimate, sub-map {sid}" + (f" (Sim(3) scale {scale:.3g})" if scale is not None else "")


def plot_trajectory(path: Path, aligned: Trajectory, ground_truth: Trajectory, t0: float,
                    scales: dict[int, float], skipped: dict[int, str],
                    span: tuple[float, float] | None = None) -> Figure:
    """Top view and height of the aligned estimate against the ground truth (drawn over
    ``span``, default the estimate's time span)."""
    fig = Figure(figsize=(12.0, 5.2), layout="constrained")
    top, height = fig.subplots(1, 2, width_ratios=(1.0, 1.25))
    span = span or (aligned.timestamps[0], aligned.timestamps[-1])
    span = (span[0] - 1e-6, span[1] + 1e-6)
    gt_in = (ground_truth.timestamps >= span[0]) & (ground_truth.timestamps <= span[1])
    gt_p, gt_t = ground_truth.positions[gt_in], ground_truth.timestamps[gt_in]
    top.plot(gt_p[:, 0], gt_p[:, 1], color=GT_COLOR, lw=3.0, alpha=0.6, label="ground truth")
    height.plot(gt_t - t0, gt_p[:, 2], color=GT_COLOR, lw=3.0, alpha=0.6, label="ground truth")
    ids = aligned.submap_ids()
    labelled: set[int] = set()
    for a, b in _blocks(ids):
        sid = int(ids[a])
        p, t = aligned.positions[a:b], aligned.timestamps[a:b]
        label = None if sid in labelled else _submap_label(sid, scales.get(sid))
        labelled.add(sid)
        top.plot(p[:, 0], p[:, 1], color=_color(sid), lw=1.4, label=label)
        top.plot(p[0, 0], p[0, 1], "o", color=_color(sid), ms=6, mfc="white")
        height.plot(t - t0, p[:, 2], color=_color(sid), lw=1.4, label=label)
    top.plot([], [], "o", color="grey", mfc="white", label="start of a sub-map")
    top.set(xlabel="x [m]", ylabel="y [m]", title="top view (Sim(3)-aligned per sub-map)")
    top.set_aspect("equal", adjustable="datalim")
    top.grid(alpha=0.3)
    height.set(xlabel="time [s]", ylabel="z [m]", title="height")
    height.grid(alpha=0.3)
    top.legend(loc="best", fontsize=8)
    if skipped:
        note = "; ".join(f"sub-map {k} not aligned: {v}" for k, v in skipped.items())
        fig.suptitle(note, fontsize=8, color="#a00")
    _save(fig, path)
    return fig


def plot_translation_error(path: Path, ate_result, rpe_result, diagnostics: Sequence[FrameDiagnostics],
                           t0: float) -> Figure:
    """ATE position error per pose and RPE translation error over time."""
    fig = Figure(figsize=(11.0, 4.6), layout="constrained")
    ax = fig.subplots()
    _shade_init(ax, diagnostics, t0)
    _mark_events(ax, diagnostics, t0)
    aligned = ate_result.aligned
    ids = aligned.submap_ids()
    for a, b in _blocks(ids):
        sid = int(ids[a])
        ax.plot(aligned.timestamps[a:b] - t0, ate_result.errors[a:b], color=_color(sid), lw=1.4,
                label=f"position error after Sim(3) alignment, sub-map {sid}")
    if rpe_result is not None and rpe_result.errors.size:
        ax.plot(rpe_result.timestamps - t0, rpe_result.errors, ".", color="black", ms=3,
                label=f"RPE translation error over Δ = {rpe_result.delta:g} s (direction only, Eq. 18-20)")
    ax.set(xlabel="time [s]", ylabel="error [m]",
           title=f"translation error: ATE RMSE {ate_result.rmse:.3f} m"
           + ("" if rpe_result is None or not math.isfinite(rpe_result.rmse)
              else f", RPE RMSE {rpe_result.rmse:.3f} m"))
    ax.set_ylim(bottom=0.0)
    ax.grid(alpha=0.3)
    fig.legend(loc="outside lower center", fontsize=8, ncol=2)
    _save(fig, path)
    return fig


def _mark_events(ax, diagnostics: Sequence[FrameDiagnostics], t0: float) -> None:
    """Shade skipped frames, mark restarts and re-initialisations (with legend entries)."""
    t = np.array([d.timestamp for d in diagnostics]) - t0
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.05
    states = np.array([d.state for d in diagnostics])
    first = {"skipped": True, "lost": True, "reinit": True}
    for k in np.flatnonzero(states == "skipped"):
        ax.axvspan(t[k] - dt / 2, t[k] + dt / 2, color="#d62728", alpha=0.25, lw=0,
                   label="skipped frame" if first.pop("skipped", False) else None)
    for state, color, label in (("lost", "#d62728", "tracking failure (restart)"),
                                ("reinit", "#ff7f0e", "re-initialisation")):
        for k in np.flatnonzero(states == state):
            ax.axvline(t[k], color=color, lw=1.2, ls="--", label=label if first.pop(state, False) else None)


def _shade_init(ax, diagnostics: Sequence[FrameDiagnostics], t0: float) -> None:
    """Grey span over the frames before the map exists (rotation-only tracking)."""
    est = [d for d in diagnostics if d.state != "skipped"]
    t = np.array([d.timestamp for d in est]) - t0
    init = np.array([d.state == "init" for d in est])
    labelled = False
    for a, b in _blocks(init.astype(np.int64)):
        if init[a]:
            ax.axvspan(t[a], t[b - 1], color="#bbbbbb", alpha=0.35, lw=0,
                       label=None if labelled else "no map yet (rotation-only tracking)")
            labelled = True


def plot_points(path: Path, diagnostics: Sequence[FrameDiagnostics], keyframe_times: Sequence[float],
                t0: float) -> Figure:
    """Tracked points, finite and infinite landmarks per frame, with the keyframes."""
    fig = Figure(figsize=(11.0, 4.6), layout="constrained")
    ax = fig.subplots()
    est = [d for d in diagnostics if d.state != "skipped"]
    t = np.array([d.timestamp for d in est]) - t0
    series = (("tracked_points", "tracked points", "#7f7f7f"),
              ("finite_landmarks", "connected finite landmarks (d > 0)", "#1f77b4"),
              ("infinite_landmarks", "connected landmarks at infinity (d = 0)", "#e377c2"))
    for name, label, color in series:
        ax.plot(t, [getattr(d, name) for d in est], color=color, lw=1.3, label=label)
    _shade_init(ax, diagnostics, t0)
    _mark_events(ax, diagnostics, t0)
    top = max([1] + [getattr(d, n) for d in est for n, _, _ in series])
    kt = np.asarray(keyframe_times, dtype=float) - t0
    ax.axhspan(-0.12 * top, -0.02 * top, color="#f2f2f2", lw=0)
    ax.plot(kt, np.full(kt.shape, -0.07 * top), "|", color="black", ms=10, mew=1.4,
            label=f"keyframes ({len(kt)})")
    ax.set_ylim(-0.12 * top, 1.05 * top)
    ax.set(xlabel="time [s]", ylabel="count", title="tracks and landmarks of the current frame")
    ax.grid(alpha=0.3)
    fig.legend(loc="outside lower center", fontsize=8, ncol=3)
    _save(fig, path)
    return fig


def plot_scale(path: Path, series, submaps: np.ndarray, lambda_t: np.ndarray | None,
               lambda_v: np.ndarray | None, diagnostics: Sequence[FrameDiagnostics], t0: float) -> Figure:
    """Relative scale error over time, one curve per sub-map (``submaps``: the sub-map of each
    sample), and Λ on its own axis when available."""
    with_lambda = lambda_t is not None and lambda_t.size > 0
    fig = Figure(figsize=(11.0, 6.8 if with_lambda else 4.4), layout="constrained")
    axes = fig.subplots(2 if with_lambda else 1, 1, sharex=True, squeeze=False)[:, 0]
    ax = axes[0]
    _mark_events(ax, diagnostics, t0)
    ax.axhline(0.0, color="black", lw=0.8)
    for a, b in _blocks(submaps):
        sid = int(submaps[a])
        ax.plot(series.timestamps[a:b] - t0, 100.0 * series.errors[a:b], color=_color(sid), lw=1.3,
                marker="." if b - a == 1 else None, label=f"relative scale error over Δ = {series.delta:g} s, sub-map {sid}")
    ax.set(ylabel="scale error [%]",
           title=f"relative scale error (estimated / true length of the last {series.delta:g} s of motion, "
                 f"aligned scale of the sub-map, minus 1); RMS {100.0 * series.rms:.2f} %")
    ax.grid(alpha=0.3)
    if with_lambda:
        lam = axes[1]
        lam.plot(lambda_t - t0, lambda_v, color="#9467bd", lw=1.3, label="Λ_scaledrift (Eq. 17)")
        lam.set(ylabel="Λ", yscale="log" if np.all(lambda_v > 0) else "linear",
                title="scale-drift indicator (diagnostics.csv)")
        lam.grid(alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    fig.legend(loc="outside lower center", fontsize=8, ncol=2)
    _save(fig, path)
    return fig


def _lambda_series(diagnostics: Sequence[FrameDiagnostics]) -> tuple[np.ndarray, np.ndarray] | None:
    """(times, Λ) of the frames with a finite ``scale_drift_indicator``; None without the column."""
    if not diagnostics or not hasattr(diagnostics[0], LAMBDA_COLUMN):
        return None
    pairs = [(d.timestamp, getattr(d, LAMBDA_COLUMN)) for d in diagnostics]
    pairs = [(t, v) for t, v in pairs if v is not None and math.isfinite(v)]
    return np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])


def write_plots(run_dir: str | Path, trajectory: Trajectory, diagnostics: Sequence[FrameDiagnostics],
                keyframe_times: Sequence[float], ground_truth: Trajectory | None,
                delta: float) -> Report:
    """Write the PNGs of a run (see the module docstring); stale ones are removed."""
    out = Path(run_dir)
    for name in PLOT_FILES:
        (out / name).unlink(missing_ok=True)
    report = Report()
    t0 = float(diagnostics[0].timestamp) if diagnostics else float(trajectory.timestamps[0])
    plot_points(out / "points.png", diagnostics, keyframe_times, t0)
    report.plots["points.png"] = "tracked points, finite and infinite landmarks, keyframes"
    lam = _lambda_series(diagnostics)
    no_gt = "no ground truth"
    if ground_truth is None:
        for name in ("trajectory.png", "translation_error.png", "scale.png"):
            report.missing[name] = no_gt
        return report
    try:
        ate_result = ate(trajectory, ground_truth, "sim3")
    except (GraniteError, ValueError) as error:
        for name in ("trajectory.png", "translation_error.png", "scale.png"):
            report.missing[name] = f"the estimate cannot be aligned to the ground truth ({error})"
        return report
    span = (t0, float(diagnostics[-1].timestamp) if diagnostics else float(trajectory.timestamps[-1]))
    plot_trajectory(out / "trajectory.png", ate_result.aligned, ground_truth, t0, ate_result.scales,
                    ate_result.skipped_submaps, span)
    report.plots["trajectory.png"] = "estimate (Sim(3)-aligned per sub-map) and ground truth"
    try:
        rpe_result = rpe(trajectory, ground_truth, delta)
    except (GraniteError, ValueError):
        rpe_result = None
    plot_translation_error(out / "translation_error.png", ate_result, rpe_result, diagnostics, t0)
    report.plots["translation_error.png"] = "position error (ATE) and RPE translation error over time"
    series = relative_scale_error(trajectory, ground_truth, delta, ate_result.scales)
    if series.errors.size:
        rows = np.clip(np.searchsorted(trajectory.timestamps, series.timestamps - 1e-9), 0, len(trajectory) - 1)
        plot_scale(out / "scale.png", series, trajectory.submap_ids()[rows],
                   *(lam if lam is not None else (None, None)), diagnostics, t0)
        report.plots["scale.png"] = "relative scale error" + (" and Λ_scaledrift" if lam is not None else "")
    else:
        report.missing["scale.png"] = f"no {delta:g} s interval with enough true motion (>= 0.1 m)"
    return report


def _metrics_table(evaluation: dict) -> list[str]:
    rows = [("ATE RMSE (Sim(3) per sub-map)", evaluation.get("ate_rmse"), "m"),
            ("ATE / path length", evaluation.get("ate_over_path_length"), "%"),
            (f"RMS RPE (Δ = {evaluation.get('delta', float('nan')):g} s, Eq. 18-20)", evaluation.get("rpe_rmse"), "m"),
            ("RMS RPE with the alignment's fixed scale (scale drift counts)",
             evaluation.get("rpe_fixed_scale_rmse"), "m"),
            ("tracking percentage", evaluation.get("tracking_percentage"), "%t"),
            ("restarts", evaluation.get("restarts"), ""),
            ("path length (ground truth)", evaluation.get("path_length"), "m"),
            ("poses evaluated (ATE) / RPE pairs",
             f"{evaluation.get('num_ate_poses')} / {evaluation.get('num_rpe_pairs')}", "")]
    lines = ["| metric | value |", "| --- | ---: |"]
    for name, value, unit in rows:
        if value is None:
            text = "n/a"
        elif unit == "%":
            text = f"{100.0 * value:.3f} %"
        elif unit == "%t":
            text = f"{value:.1f} %"
        elif isinstance(value, float):
            text = f"{value:.4f} {unit}".strip()
        else:
            text = f"{value} {unit}".strip()
        lines.append(f"| {name} | {text} |")
    scales = evaluation.get("submap_scales") or {}
    if scales:
        lines.append("| Sim(3) scale per sub-map | " + ", ".join(f"{k}: {v:.4g}" for k, v in scales.items()) + " |")
    return lines


def report_markdown(title: str, header: Sequence[str], summary: dict, evaluation: dict | None,
                    evaluation_error: str | None, plots: Report, image_prefix: str = "") -> str:
    """The text of ``report.md``; images are linked as ``image_prefix + name``."""
    lines = [f"# {title}", "", *[f"- {h}" for h in header], ""]
    lines += ["## Run", "",
              f"- frames: {summary['frames']} ({summary['estimated_frames']} estimated, "
              f"{summary['skipped_frames']} skipped: no pose, not in `trajectory.tum`)",
              f"- restarts: {summary['restarts']}, sub-maps: {summary['submaps']}, keyframes: {summary['keyframes']}",
              f"- VO time: {summary['mean_processing_ms']:.1f} ms per frame"
              + (f" ({summary['frames_per_second']:.1f} fps)" if summary.get("frames_per_second") else "")]
    if summary.get("gn_mean_iterations") is not None:
        lines.append(f"- Gauss-Newton: {summary['gn_mean_iterations']:.1f} iterations per frame; the main "
                     f"optimisation used all its iterations without converging on "
                     f"{summary['gn_unconverged_frames']} of {summary['gn_optimized_frames']} frames")
    if "scale_drift_defined_frames" in summary:
        line = f"- Λ_scaledrift defined on {summary['scale_drift_defined_frames']} frames"
        if summary.get("scale_drift_no_scale_frames"):
            line += (f"; **no scale information on {summary['scale_drift_no_scale_frames']} frames**: "
                     "nothing carries the map's scale there, the scale drift is unbounded "
                     "(`scale_drift_reason` in `diagnostics.csv`)")
        lines.append(line)
    if summary.get("skipped_by_reason") or summary.get("frontend_rejections"):
        reasons = {**summary.get("skipped_by_reason", {}), **summary.get("frontend_rejections", {})}
        lines.append("- skipped: " + "; ".join(f"{n} × {r}" for r, n in reasons.items()))
    if summary.get("warnings"):
        lines.append(f"- warnings: {summary['warning_count']} in {len(summary['warnings'])} kind(s) "
                     "(listed in `summary.json`): "
                     + "; ".join(f"{w['count']} × {w['kind']}: {w['message']}" for w in summary["warnings"]))
    if summary.get("interrupted"):
        lines.append("- **interrupted**: the outputs hold the frames processed before Ctrl-C")
    lines += ["", "## Evaluation", ""]
    if evaluation is not None:
        lines += _metrics_table(evaluation)
    elif evaluation_error is not None:
        lines.append(f"Evaluation failed, no `evaluation.json` was written: {evaluation_error}")
    else:
        lines.append("No ground truth: no evaluation.")
    lines += ["", "## Plots", ""]
    for name in PLOT_FILES:  # in this order, whatever order they were drawn in
        if name in plots.plots:
            caption = plots.plots[name]
            lines += [f"![{caption}]({image_prefix}{name})", "", f"*{caption}* (`{name}`)", ""]
    for name, reason in plots.missing.items():
        lines += [f"- `{name}` not written: {reason}"]
    return "\n".join(lines).rstrip() + "\n"


def write_report(path: str | Path, text: str) -> None:
    """Atomically write a report."""
    atomic_write_text(path, text)
