"""Do two checkouts give the same `granite run` outputs, byte for byte? (For speed work: an
optimisation must not change a single bit of the trajectories or diagnostics.)

    python tools/compare_runs.py --a /work/main --b . --out /tmp/cmp DATASET [DATASET ...]

For every dataset, ``granite run --quiet`` runs once with each checkout's code
(``PYTHONPATH=<checkout>``, one run after the other) into ``OUT/a/<name>`` and ``OUT/b/<name>``
(``--reuse`` keeps run folders that are already there, e.g. the reference side of an earlier
call; ``--sequential`` is passed on). Then, per dataset, ``trajectory.tum``, ``submaps.csv``
and ``keyframes.csv`` are compared byte for byte, ``diagnostics.csv`` without its timing
column (``processing_ms``), and ``landmarks.npz`` array by array (dtype, shape, bytes). One line
per file; exit status 0 when everything is identical, 1 when something differs or a run
failed, 2 for bad input.
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

SAME_BYTES = ("trajectory.tum", "submaps.csv", "keyframes.csv")
TIMING_COLUMNS = {"processing_ms"}


def run_granite(code: Path, dataset: Path, out: Path, sequential: bool) -> int:
    env = dict(os.environ, PYTHONPATH=str(code))
    cmd = [sys.executable, "-c", "import sys; from granite.cli.main import main; sys.exit(main())",
           "run", "--quiet", "--out", str(out), str(dataset)]
    if sequential:
        cmd.append("--sequential")
    log = out.parent / f"{out.name}.log"
    with open(log, "w") as f:
        return subprocess.run(cmd, env=env, stdout=f, stderr=subprocess.STDOUT).returncode


def diagnostics_rows(path: Path) -> list[list[str]]:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    drop = {i for i, name in enumerate(rows[0]) if name in TIMING_COLUMNS} if rows else set()
    return [[c for i, c in enumerate(row) if i not in drop] for row in rows]


def same_npz(a: Path, b: Path) -> bool:
    with np.load(a) as x, np.load(b) as y:
        if sorted(x.files) != sorted(y.files):
            return False
        return all(x[k].dtype == y[k].dtype and x[k].shape == y[k].shape
                   and x[k].tobytes() == y[k].tobytes() for k in x.files)


def compare(a: Path, b: Path) -> list[tuple[str, bool]]:
    out = []
    for name in SAME_BYTES:
        out.append((name, (a / name).read_bytes() == (b / name).read_bytes()))
    out.append(("diagnostics.csv", diagnostics_rows(a / "diagnostics.csv")
                == diagnostics_rows(b / "diagnostics.csv")))
    out.append(("landmarks.npz", same_npz(a / "landmarks.npz", b / "landmarks.npz")))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("datasets", nargs="+", type=Path)
    parser.add_argument("--a", type=Path, required=True, help="reference checkout")
    parser.add_argument("--b", type=Path, required=True, help="checkout under test")
    parser.add_argument("--out", type=Path, required=True, help="folder for the run folders")
    parser.add_argument("--reuse", action="store_true", help="keep existing run folders")
    parser.add_argument("--sequential", action="store_true", help="granite run --sequential")
    args = parser.parse_args()
    for code in (args.a, args.b):
        if not (code / "granite" / "__init__.py").is_file():
            print(f"error: {code} is not a checkout (no granite/__init__.py)", file=sys.stderr)
            return 2
    names = [d.resolve().name for d in args.datasets]
    for d in args.datasets:
        if not (d / "mav0").is_dir():
            print(f"error: {d} is not a dataset folder (no mav0/)", file=sys.stderr)
            return 2
    if len(set(names)) != len(names):
        print("error: two datasets have the same folder name", file=sys.stderr)
        return 2
    status = 0
    for dataset, name in zip(args.datasets, names):
        runs = {}
        for side, code in (("a", args.a), ("b", args.b)):
            out = args.out / side / name
            runs[side] = out
            if args.reuse and (out / "trajectory.tum").is_file():
                continue
            out.parent.mkdir(parents=True, exist_ok=True)
            rc = run_granite(code.resolve(), dataset.resolve(), out, args.sequential)
            if rc != 0:
                print(f"FAILED {name}: granite run with {code} exited with {rc} "
                      f"(log: {out.parent / (name + '.log')})")
                status = 1
        if not all((r / "trajectory.tum").is_file() for r in runs.values()):
            status = 1
            continue
        for file, same in compare(runs["a"], runs["b"]):
            print(f"{'same  ' if same else 'DIFFER'} {name}/{file}", flush=True)
            status |= 0 if same else 1
    print("all identical" if status == 0 else "DIFFERENCES (or failed runs)")
    return status


if __name__ == "__main__":
    raise SystemExit(main())
