"""How far one run's accuracy is from the next: the VO's spread under round-off-sized changes.

    python benchmarks/bench_spread.py DATASET [DATASET ...] --out DIR [--runs 15]
                                      [--step 0.01] [--config FILE] [--fail-ate 1.0]

The VO is deterministic, but on a hard flight (a fast turn that nearly empties the map, a
two-view initialisation between twin solutions) a change of the last bits of one sum can
decide between keeping the map and losing it. A single run then says little about a code
change that is not bit-identical: the change moves the run to another draw of the same
distribution. This script runs ``granite run`` ``--runs`` times per dataset, each time with
``[backend] landmark_damping`` (1e-9 by default, a numerical safeguard whose value does not
matter at this size) multiplied by ``1 + step * s`` for ``s = 0, +1, -1, +2, -2, ...``: a
perturbation of the landmark blocks about 1e-11 of their size, i.e. round-off. It prints per
dataset the median and quartiles of the ATE (Sim(3), m) and RMS RPE (Eq. 18-20, m), the
number of runs with ATE above ``--fail-ate`` metres and of runs with restarts, and writes
DIR/spread.json (every run's figures) and DIR/<dataset>/<s>/ (the run folders; an existing run
folder with evaluation.json is reused, so an interrupted study resumes). Compare two code
versions by running the script from each checkout's folder on the same datasets, into
different --out folders: the runs are ``python -m granite.cli.main run`` processes, which
import the ``granite`` of the current folder first.

Bad input (missing dataset, unreadable configuration, --runs < 1) is one error line and exit
status 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `granite run`

import numpy as np  # noqa: E402

from granite.estimator.config import ConfigError, VoConfig  # noqa: E402
from granite.io.atomic import atomic_write_text  # noqa: E402


def perturbation_steps(runs: int) -> list[int]:
    """``0, +1, -1, +2, -2, ...``: the multiples of ``--step`` of each run."""
    steps = [0]
    k = 1
    while len(steps) < runs:
        steps.append(k)
        if len(steps) < runs:
            steps.append(-k)
        k += 1
    return steps


def perturbed_config(base: VoConfig, step: float, s: int) -> VoConfig:
    """``base`` with ``landmark_damping`` scaled by ``1 + step * s``."""
    backend = dataclasses.replace(base.backend,
                                  landmark_damping=base.backend.landmark_damping * (1.0 + step * s))
    return dataclasses.replace(base, backend=backend)


def run_one(dataset: Path, run_dir: Path, config: VoConfig) -> dict:
    """One ``granite run`` (skipped when ``run_dir`` already holds its evaluation)."""
    evaluation = run_dir / "evaluation.json"
    if not evaluation.exists():
        run_dir.mkdir(parents=True, exist_ok=True)
        config_path = run_dir.parent / f"{run_dir.name}.toml"
        atomic_write_text(config_path, config.to_toml())
        proc = subprocess.run([sys.executable, "-m", "granite.cli.main", "run", str(dataset),
                               "--out", str(run_dir), "--config", str(config_path), "--quiet"],
                              capture_output=True, text=True)
        if proc.returncode != 0 or not evaluation.exists():
            last = (proc.stderr.strip().splitlines() or ["no message"])[-1]
            raise RuntimeError(f"{dataset}: granite run failed ({last})")
    e = json.loads(evaluation.read_text())
    return {"ate_rmse": float(e["ate_rmse"]), "rpe_rmse": float(e["rpe_rmse"]),
            "restarts": int(e.get("restarts", 0))}


def summarize(rows: list[dict], fail_ate: float) -> dict:
    """Median and quartiles of ATE and RPE, runs with ATE above ``fail_ate``, runs with
    restarts."""
    ate = np.array([r["ate_rmse"] for r in rows])
    rpe = np.array([r["rpe_rmse"] for r in rows])
    return {
        "runs": len(rows),
        "ate_quartiles": [float(x) for x in np.percentile(ate, [25, 50, 75])],
        "rpe_quartiles": [float(x) for x in np.percentile(rpe, [25, 50, 75])],
        "ate_above": int(np.sum(ate > fail_ate)),
        "with_restarts": int(sum(r["restarts"] > 0 for r in rows)),
        "first_run": rows[0],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="See the module docstring for details.")
    parser.add_argument("datasets", nargs="+", type=Path, help="dataset folders")
    parser.add_argument("--out", type=Path, required=True, help="folder for the runs and spread.json")
    parser.add_argument("--runs", type=int, default=15, help="runs per dataset (default 15)")
    parser.add_argument("--step", type=float, default=0.01,
                        help="relative change of landmark_damping between runs (default 0.01)")
    parser.add_argument("--config", type=Path, help="VO configuration (default: the defaults)")
    parser.add_argument("--fail-ate", type=float, default=1.0,
                        help="an ATE above this many metres counts as a broken run (default 1)")
    args = parser.parse_args(argv)
    try:
        if args.runs < 1:
            raise ValueError("--runs must be at least 1")
        if not 0.0 < args.step < 0.1:
            raise ValueError("--step must be in (0, 0.1)")
        for d in args.datasets:
            if not d.is_dir():
                raise ValueError(f"{d}: dataset folder not found")
        base = VoConfig.load(args.config) if args.config else VoConfig()
        args.out.mkdir(parents=True, exist_ok=True)
    except (ValueError, ConfigError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    steps = perturbation_steps(args.runs)
    results = {}
    print(f"{'dataset':32s} runs  ATE [m] q25 / median / q75   RPE [m] q25 / median / q75   "
          f"ATE > {args.fail_ate:g} m  restarts  first run ATE / RPE")
    for d in args.datasets:
        rows = []
        for i, s in enumerate(steps):
            print(f"  {d.name}: run {i + 1}/{len(steps)} (damping x {1 + args.step * s:.2f})",
                  end="\r", file=sys.stderr, flush=True)
            row = run_one(d.resolve(), args.out / d.name / f"{s:+d}",
                          perturbed_config(base, args.step, s))
            rows.append({"step": s, **row})
        summary = summarize(rows, args.fail_ate)
        results[d.name] = {"summary": summary, "runs": rows}
        a, r = summary["ate_quartiles"], summary["rpe_quartiles"]
        print(f"{d.name:32s} {summary['runs']:4d}  {a[0]:7.3f} / {a[1]:7.3f} / {a[2]:7.3f}   "
              f"{r[0]:7.3f} / {r[1]:7.3f} / {r[2]:7.3f}   {summary['ate_above']:10d}  "
              f"{summary['with_restarts']:8d}  {rows[0]['ate_rmse']:.3f} / {rows[0]['rpe_rmse']:.3f}")
    atomic_write_text(args.out / "spread.json", json.dumps(results, indent=1))
    print(f"results: {args.out / 'spread.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
