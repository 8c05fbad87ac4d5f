"""Aggregation of a study: ``results.csv``, ``report.md`` with the paper-style tables (Table I:
failures per sequence and variant; Table II: RMS RPE), and the PNG plots."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from granite.bench.study import Study
from granite.bench.tasks import RESULT_COLUMNS, TIMING_COLUMNS, run_dir
from granite.estimator.diagnostics import csv_cell
from granite.io import atomic_path, atomic_write_text


def results_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(RESULT_COLUMNS)
    for row in rows:
        writer.writerow([csv_cell(row.get(c)) for c in RESULT_COLUMNS])
    return buf.getvalue()


def read_results(path: str | Path, timing: bool = True) -> list[dict]:
    """The rows of a results.csv as strings; without the TIMING_COLUMNS unless ``timing``."""
    with Path(path).open(newline="", encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle))
    if not timing:
        for row in rows:
            for c in TIMING_COLUMNS:
                row.pop(c, None)
    return rows


def _seq_label(study: Study, seq) -> str:
    seed = "" if seq.seed is None else f" seed {seq.seed}"
    frames = f" ({seq.frames})" if seq.frames != "all" else ""
    return f"{seq.label}{seed}{frames}"


def _fmt(v, digits: int = 3, scale: float = 1.0, suffix: str = "") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return f"{scale * v:.{digits}f}{suffix}"


def _mean(values) -> float | None:
    vals = [v for v in values if v is not None]
    return sum(vals) / len(vals) if vals else None


def _table(study: Study, by: dict, title: str, cell, total_label: str, total) -> list[str]:
    names = [v.name for v in study.variants]
    lines = [f"### {title}", "", "| sequence | " + " | ".join(names) + " |",
             "| --- |" + " ---: |" * len(names)]
    for seq in study.sequences:
        cells = [cell(by.get((seq.id, n))) for n in names]
        lines.append(f"| {_seq_label(study, seq)} | " + " | ".join(cells) + " |")
    lines.append(f"| **{total_label}** | " + " | ".join(
        total([by.get((s.id, n)) for s in study.sequences]) for n in names) + " |")
    return lines + [""]


def _ok(row) -> bool:
    return row is not None and row.get("status") == "ok"


def report_markdown(study: Study, rows: list[dict], plots: dict[str, str]) -> str:
    by = {(r["sequence"], r["variant"]): r for r in rows}
    d = f"{study.delta:g}"
    lines = [f"# granite bench: {study.name}", ""]
    if study.description:
        lines += [study.description, ""]
    lines += [f"study file: `{study.source}`; {len(study.sequences)} sequences x {len(study.variants)} "
              f"variants = {len(rows)} runs; RPE Δ = {d} s (paper Eq. 18-20), ATE after "
              f"{study.align} alignment per sub-map.", "", "Variants:", ""]
    lines += [f"- {v.label()}" for v in study.variants] + [""]
    failed = [r for r in rows if r.get("status") != "ok"]
    if failed:
        lines += ["Runs without metrics:", ""]
        lines += [f"- {r['sequence']} / {r['variant']}: {r.get('status')}" for r in failed] + [""]

    def failures(r):
        return "failed" if r is None or r.get("restarts") is None else str(r["restarts"])

    lines += _table(study, by, "Table I: failures (restarts after tracking loss) per sequence", failures,
                    "total", lambda rs: str(sum(r["restarts"] for r in rs if r and r.get("restarts") is not None)))
    lines += _table(study, by, "Tracking % (longest sub-map / run duration)",
                    lambda r: _fmt(r.get("tracking_percentage"), 1) if _ok(r) else "n/a", "mean",
                    lambda rs: _fmt(_mean(r.get("tracking_percentage") for r in rs if _ok(r)), 1))
    lines += _table(study, by, f"Table II: RMS RPE (Δ = {d} s) [m]",
                    lambda r: _fmt(r.get("rpe_rmse")) if _ok(r) else "n/a", "mean",
                    lambda rs: _fmt(_mean(r.get("rpe_rmse") for r in rs if _ok(r))))
    lines += _table(study, by, f"RMS RPE (Δ = {d} s) with each sub-map's alignment scale fixed (scale drift counts) [m]",
                    lambda r: _fmt(r.get("rpe_fixed_scale_rmse")) if _ok(r) else "n/a", "mean",
                    lambda rs: _fmt(_mean(r.get("rpe_fixed_scale_rmse") for r in rs if _ok(r))))
    lines += _table(study, by, "ATE / path length",
                    lambda r: _fmt(r.get("ate_over_path_length"), 2, 100, " %") if _ok(r) else "n/a", "mean",
                    lambda rs: _fmt(_mean(r.get("ate_over_path_length") for r in rs if _ok(r)), 2, 100, " %"))
    lines += _table(study, by, "Initialisation delay [frames]",
                    lambda r: str(r["init_delay_frames"]) if _ok(r) and r.get("init_delay_frames") is not None
                    else "n/a", "mean",
                    lambda rs: _fmt(_mean(r.get("init_delay_frames") for r in rs if _ok(r)), 1))
    lines += _table(study, by, "Λ_scaledrift (Eq. 17): median over tracked frames (defined on % of them)",
                    lambda r: (f"{r['lambda_median']:.3g} ({r['lambda_defined_percentage']:.0f} %)"
                               if r and r.get("lambda_median") is not None else "n/a"), "mean of medians",
                    lambda rs: _fmt(_mean(r.get("lambda_median") for r in rs if r), 3))
    lines += _table(study, by, "VO fps (median frame time; depends on the machine and its load)",
                    lambda r: _fmt(r.get("vo_fps"), 1) if r else "n/a", "mean",
                    lambda rs: _fmt(_mean(r.get("vo_fps") for r in rs if r), 1))
    lines += ["## Plots", ""]
    for name, caption in plots.items():
        lines += [f"**{caption}**", "", f"![{caption}]({name})", ""]
    lines += ["Every run folder (trajectory, diagnostics, evaluation, plots, report) is in `runs/<sequence>/<variant>/`; "
              "the rows are in `results.csv`.", ""]
    return "\n".join(lines)


def _save(fig, path: Path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)


def plot_metrics(study: Study, rows: list[dict], path: Path) -> None:
    """Failures, RMS RPE and ATE / path per variant: one dot per sequence, bar = mean (total)."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    names = [v.name for v in study.variants]
    metrics = (("restarts", "failures (restarts), total", 1.0, sum),
               ("rpe_rmse", f"RMS RPE (Δ={study.delta:g} s) [m], mean", 1.0, _mean),
               ("ate_over_path_length", "ATE / path [%], mean", 100.0, _mean))
    fig = Figure(figsize=(4.2 * len(metrics), 4.0), layout="constrained")
    axes = fig.subplots(1, len(metrics))
    for ax, (key, title, scale, agg) in zip(axes, metrics):
        for i, name in enumerate(names):
            vals = [scale * r[key] for r in rows if r["variant"] == name and r.get(key) is not None]
            if vals:
                ax.bar(i, agg(vals), color="#9ecae1", width=0.6)
                ax.plot([i] * len(vals), vals, "o", color="#08519c", ms=4)
        ax.set_xticks(range(len(names)), names, rotation=20)
        if key == "restarts":
            ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_title(title, fontsize=10)
        ax.grid(axis="y", alpha=0.3)
    _save(fig, path)


def plot_trajectories(study: Study, out: Path, seq, path: Path) -> bool:
    """Top view of the ground truth and every variant's estimate (aligned per sub-map)."""
    import numpy as np
    from matplotlib.figure import Figure

    from granite.errors import GraniteError
    from granite.evaluation import ate
    from granite.io import open_dataset, read_estimate

    gt = open_dataset(seq.folder(out)).ground_truth
    fig = Figure(figsize=(6.5, 5.5), layout="constrained")
    ax = fig.subplots()
    drawn = False
    lo, hi = math.inf, -math.inf
    for k, variant in enumerate(study.variants):
        try:
            est, _ = read_estimate(run_dir(out, seq, variant))
            aligned = ate(est, gt, study.align).aligned
        except (GraniteError, ValueError, OSError):
            continue
        p, ids = aligned.positions, aligned.submap_ids()
        starts = [0, *(np.flatnonzero(np.diff(ids)) + 1), len(ids)]
        for j, (a, b) in enumerate(zip(starts[:-1], starts[1:])):  # one line per sub-map
            ax.plot(p[a:b, 0], p[a:b, 1], lw=1.2, color=f"C{k}",
                    label=variant.name + (f" ({len(starts) - 1} sub-maps)" if len(starts) > 2 else "")
                    if j == 0 else None)
        lo, hi = min(lo, est.timestamps[0]), max(hi, est.timestamps[-1])
        drawn = True
    if not drawn:
        return False
    inside = (gt.timestamps >= lo - 1e-6) & (gt.timestamps <= hi + 1e-6)
    ax.plot(gt.positions[inside, 0], gt.positions[inside, 1], color="#2ca02c", lw=3, alpha=0.45,
            label="ground truth", zorder=0)
    ax.set(xlabel="x [m]", ylabel="y [m]", title=f"{_seq_label(study, seq)}: top view ({study.align} per sub-map)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    _save(fig, path)
    return True


def aggregate(out: Path, study: Study, rows: list[dict]) -> dict:
    """Write results.csv, the plots and report.md into ``out``; rows in table order."""
    out = Path(out)
    order = {(s.id, v.name): i for i, (s, v) in enumerate(study.runs())}
    rows = sorted(rows, key=lambda r: order.get((r["sequence"], r["variant"]), len(order)))
    atomic_write_text(out / "results.csv", results_csv(rows))
    plots: dict[str, str] = {}
    plot_metrics(study, rows, out / "metrics.png")
    plots["metrics.png"] = "failures, RMS RPE and ATE / path per variant (dots: sequences)"
    (out / "trajectories").mkdir(exist_ok=True)
    for seq in study.sequences:
        name = f"trajectories/{seq.id}.png"
        if plot_trajectories(study, out, seq, out / name):
            plots[name] = f"trajectories: {_seq_label(study, seq)}"
    atomic_write_text(out / "report.md", report_markdown(study, rows, plots))
    return {"kind": "aggregate", "rows": len(rows), "plots": len(plots)}
