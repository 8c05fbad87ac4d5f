"""The tasks of a study, as plain functions a Dask worker (or the serial runner) calls.

Every task is idempotent: it writes its outputs atomically and a marker file last, so a task
repeated after a worker failure (Dask reschedules the tasks of a lost worker) or after an
interrupted study does the same work again or finds it done; nothing half-written is ever read.

Rendering runs Blender in a subprocess (``python -m simulation.cli render FILE --frames A:B``),
never in the worker's own process: ``bpy`` is one Blender instance per process, not thread-safe,
holds its scene in global state, takes seconds to import and hundreds of MB; a subprocess per task
keeps the worker light for the VO tasks, frees Blender's memory after each task, and a Blender
crash fails one task (retried) instead of killing the worker. Each frame is written atomically by
:class:`simulation.writer.RunWriter` (depth, then image: the image completes the frame), and a
render of frames that exist skips them, so a repeated task is harmless.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

from granite.bench.study import Sequence, Variant
from granite.errors import GraniteError
from granite.io import atomic_write_text

#: Columns of results.csv, in order. TIMING_COLUMNS differ between two runs of the same study
#: (they measure this machine at that moment); every other column is deterministic.
RESULT_COLUMNS = (
    "sequence", "scenario", "seed", "frames", "variant", "status", "images", "estimated_frames",
    "restarts", "tracking_percentage", "init_delay_frames", "init_delay_s", "rpe_rmse", "ate_rmse",
    "ate_over_path_length", "path_length", "num_rpe_pairs", "rpe_fixed_scale_rmse", "lambda_defined_percentage",
    "lambda_median", "lambda_ref_median", "gn_iterations_mean", "gn_unconverged_percentage",
    "vo_fps", "vo_wall_s",
)
TIMING_COLUMNS = ("vo_fps", "vo_wall_s")
MARKERS = ".bench"  # folder of task markers inside a sequence or run folder
ROW_FILE = "bench_row.json"

_ROOT = Path(__file__).resolve().parent.parent.parent  # folder holding granite/ and simulation/


def run_dir(out: Path, seq: Sequence, variant: Variant) -> Path:
    return Path(out) / "runs" / seq.id / variant.slug


def render_marker(out: Path, seq: Sequence, a: int, b: int) -> Path:
    return seq.folder(Path(out)) / MARKERS / f"render-{a}-{b}.done"


def complete_marker(out: Path, seq: Sequence) -> Path:
    return seq.folder(Path(out)) / MARKERS / "complete.json"


def vo_marker(out: Path, seq: Sequence, variant: Variant) -> Path:
    return run_dir(out, seq, variant) / MARKERS / "vo.json"


def config_fingerprint(variant: Variant) -> str:
    """SHA-256 (16 hex digits) of the variant's complete VO configuration (TOML, ablations
    included): a finished run counts only for the configuration that made it."""
    import hashlib

    return hashlib.sha256(variant.build().to_toml().encode("utf-8")).hexdigest()[:16]


def vo_done(out: Path, seq: Sequence, variant: Variant) -> bool:
    """Whether the run folder holds a finished run of the variant's current configuration (a
    run of an edited variant, or of a marker without a fingerprint, is done again)."""
    marker = vo_marker(out, seq, variant)
    if not marker.is_file():
        return False
    try:
        recorded = json.loads(marker.read_text(encoding="utf-8")).get("config")
    except (OSError, ValueError):
        return False
    return recorded == config_fingerprint(variant)


def _render(out: Path, seq: Sequence, frames: str) -> str:
    """``granite-sim render`` of ``frames`` of the sequence in a subprocess; its stderr summary."""
    cmd = [sys.executable, "-m", "simulation.cli", "render", str(seq.scenario_file(out)),
           "--out", str(seq.folder(out)), "--frames", frames, "--quiet"]
    if seq.width is not None:
        cmd += ["--width", str(seq.width)]
    if seq.height is not None:
        cmd += ["--height", str(seq.height)]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(_ROOT), env.get("PYTHONPATH", "")) if p)
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        tail = " | ".join((proc.stderr or proc.stdout).strip().splitlines()[-3:])
        raise RuntimeError(f"rendering {seq.id} frames {frames} failed (exit {proc.returncode}): {tail}")
    return proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else ""


def render_chunk(out: Path, seq: Sequence, a: int, b: int) -> dict:
    """Render frames [a, b) of a sequence (finished frames are skipped)."""
    t0 = time.perf_counter()
    message = _render(Path(out), seq, f"{a}:{b}")
    atomic_write_text(render_marker(out, seq, a, b), message + "\n")
    return {"kind": "render", "sequence": seq.id, "frames": f"{a}:{b}",
            "seconds": time.perf_counter() - t0, "message": message}


def finalize_sequence(out: Path, seq: Sequence, *renders) -> dict:
    """After all render tasks of a sequence: one more render of the whole window, which finds
    every frame done and rewrites the image lists and the manifest from the files present (the
    render tasks wrote them concurrently; the last writer need not have seen every frame), or
    renders a frame still missing. Checks the dataset then has every frame of the window."""
    from granite.io import open_dataset

    t0 = time.perf_counter()
    message = _render(Path(out), seq, seq.frames)
    folder = seq.folder(Path(out))
    manifest = json.loads((folder / "manifest.json").read_text(encoding="utf-8"))
    a, b = seq.frame_range
    expected = sum(1 for f in manifest["frames"][a:b] if not f["dropped"])
    images = len(open_dataset(folder))
    if images != expected:
        raise RuntimeError(f"{folder}: {images} images after rendering, expected {expected}")
    atomic_write_text(complete_marker(out, seq), json.dumps(
        {"frames": seq.frames, "fingerprint": seq.fingerprint, "images": images}) + "\n")
    return {"kind": "finalize", "sequence": seq.id, "seconds": time.perf_counter() - t0,
            "message": message, "images": images}


def run_vo(out: Path, seq: Sequence, variant: Variant, delta: float, *deps) -> dict:
    """One VO run (``granite run``'s :func:`~granite.cli.run_cmd.perform_run`: run folder with
    trajectory, diagnostics, evaluation, plots and report) of a variant on a sequence. It runs
    the VO's sequential mode (bit-identical to the concurrent one): the cluster already gives
    each core a single-threaded worker, and the frame pipeline's extra threads would only
    compete with the other workers."""
    from granite.cli.run_cmd import perform_run
    from granite.io import open_dataset

    target = run_dir(out, seq, variant)
    t0 = time.perf_counter()
    dataset = open_dataset(seq.folder(Path(out)))
    perform_run(dataset, variant.build(), target, None, delta=delta, progress=False,
                config_label=variant.label(), concurrent=False)
    wall = time.perf_counter() - t0
    atomic_write_text(vo_marker(out, seq, variant),
                      json.dumps({"wall_s": wall, "config": config_fingerprint(variant)}) + "\n")
    return {"kind": "vo", "sequence": seq.id, "variant": variant.name, "seconds": wall}


def _finite(x) -> float | None:
    return None if x is None or not math.isfinite(float(x)) else float(x)


def _median(values: list[float]) -> float | None:
    import numpy as np

    return float(np.median(values)) if values else None


def base_row(seq: Sequence, variant: Variant) -> dict:
    row = dict.fromkeys(RESULT_COLUMNS)
    row.update(sequence=seq.id, scenario=seq.label, seed=seq.seed, frames=seq.frames, variant=variant.name)
    return row


def evaluate_run(out: Path, seq: Sequence, variant: Variant, delta: float, align: str, *deps) -> dict:
    """The results.csv row of a run, from its folder: the metrics of ``granite eval`` (ATE with
    ``align`` per sub-map, RPE over ``delta`` s, tracking percentage, restarts), the
    initialisation delay, Λ_scaledrift figures and the VO's frame rate. Written to the run
    folder's ``bench_row.json`` (with ``delta`` and ``align``: a study with other settings
    evaluates again)."""
    from granite.estimator.diagnostics import read_diagnostics
    from granite.evaluation import evaluate
    from granite.evaluation.initialization import initialization_delay
    from granite.io import open_dataset, read_estimate

    out = Path(out)
    folder = run_dir(out, seq, variant)
    row = base_row(seq, variant)
    diags = read_diagnostics(folder / "diagnostics.csv")
    summary = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
    row["images"] = summary["frames"]
    row["estimated_frames"] = summary["estimated_frames"]
    row["restarts"] = summary["restarts"]
    ms = [d.processing_ms for d in diags if d.state != "skipped"]
    row["vo_fps"] = 1000.0 / _median(ms) if ms else None
    marker = vo_marker(out, seq, variant)
    if marker.is_file():
        row["vo_wall_s"] = json.loads(marker.read_text(encoding="utf-8"))["wall_s"]
    tracked = [d for d in diags if d.state in ("tracking", "reinit")]
    lam = [d.scale_drift_indicator for d in tracked if d.scale_drift_indicator is not None]
    lam_ref = [d.scale_drift_indicator_ref for d in tracked if d.scale_drift_indicator_ref is not None]
    if tracked:
        row["lambda_defined_percentage"] = 100.0 * len(lam) / len(tracked)
    row["lambda_median"] = _median(lam)
    row["lambda_ref_median"] = _median(lam_ref)
    optimized = [d for d in diags if d.gn_converged is not None]
    if optimized:
        row["gn_iterations_mean"] = sum(d.gn_iterations for d in optimized) / len(optimized)
        row["gn_unconverged_percentage"] = 100.0 * sum(not d.gn_converged for d in optimized) / len(optimized)
    try:
        gt = open_dataset(seq.folder(out)).ground_truth
        est, _ = read_estimate(folder)
        ev = evaluate(est, gt, delta=delta, align=align).to_dict()
        init = initialization_delay([d.timestamp for d in diags], [d.state for d in diags], gt).to_dict()
    except (GraniteError, ValueError) as error:
        row["status"] = f"evaluation failed: {error}"
    else:
        row["status"] = "ok"
        for key in ("restarts", "tracking_percentage", "rpe_rmse", "ate_rmse", "ate_over_path_length",
                    "path_length", "num_rpe_pairs", "rpe_fixed_scale_rmse"):
            row[key] = ev[key]
        row["init_delay_frames"] = init.get("init_delay_frames")
        row["init_delay_s"] = init.get("init_delay_s")
    for key, v in row.items():
        if isinstance(v, float):
            row[key] = _finite(v)
    atomic_write_text(folder / ROW_FILE, json.dumps({"delta": delta, "align": align, "row": row}, indent=1) + "\n")
    return row


def read_row(out: Path, seq: Sequence, variant: Variant, delta: float, align: str) -> dict | None:
    """The row of a finished evaluation with the same settings, else None."""
    path = run_dir(out, seq, variant) / ROW_FILE
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return None
    if data.get("delta") != delta or data.get("align") != align or not vo_marker(out, seq, variant).is_file():
        return None
    return data["row"]
