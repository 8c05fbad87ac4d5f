"""Map-initialisation delay against what the parallax threshold allows (issue 12).

    python benchmarks/bench_init.py DATASET [DATASET ...] [--config FILE]

Per dataset the VO runs in-process (as ``granite run``, sequential mode) and the table gives,
in processed frames: the *onset* of ``evaluation.json`` (the first frame 5 cm of ground-truth
baseline from an earlier one), the *parallax-available* frame (the first frame whose
ground-truth baseline to an earlier frame j reaches ``2 rho_j tan(alpha / 2)``, paper Eq. 8,
with ``rho_j`` the median rendered depth of frame j and ``alpha`` the configuration's
``[initialization] min_parallax_deg``: no two-view initialisation with that threshold can
accept before it), the frame whose state first is ``tracking``, and the two delays. Datasets
without depth maps (real sequences) get only the onset delay. Ground truth is required.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _vo_datasets import parse_config_and_datasets  # noqa: E402

import numpy as np  # noqa: E402


def _median_depths(ds) -> np.ndarray | None:
    """Median valid rendered depth [m] per frame (NaN where a frame has none), or None without
    depth maps."""
    from simulation.depth import depth_reader

    depth_of = depth_reader(ds)
    if depth_of is None:
        return None
    out = np.full(len(ds), np.nan)
    for i in range(len(ds)):
        d = depth_of(i)
        if d is not None:
            ok = np.isfinite(d) & (d > 0)
            out[i] = float(np.median(d[ok])) if ok.any() else np.nan
    return out


def main(argv=None) -> int:
    parsed = parse_config_and_datasets(__doc__.splitlines()[0], argv)
    if parsed is None:
        return 2
    config, datasets = parsed
    from granite.estimator.runner import run_vo
    from granite.evaluation.initialization import initialization_delay, parallax_available

    alpha = config.initialization.min_parallax_deg
    print(f"parallax threshold {alpha:g} deg (Eq. 8); frames are processed frames\n")
    print("| dataset | onset (5 cm) | parallax available | first tracking | delay from onset | delay from parallax available |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for ds in datasets:
        result = run_vo(ds, config, progress=False, concurrent=False)
        ts = np.array([d.timestamp for d in result.diagnostics])
        states = [d.state for d in result.diagnostics]
        delay = initialization_delay(ts, states, ds.ground_truth)
        depths = _median_depths(ds)
        avail = None
        if depths is not None:
            index = {float(t): i for i, t in enumerate(ds.timestamps)}
            kept = np.array([s != "skipped" for s in states])  # indices as initialization_delay's
            rho = np.array([depths[index[float(t)]] for t in ts[kept]])
            avail = parallax_available(ts[kept], ds.ground_truth, rho, alpha)
        first = delay.tracking_frame

        def fmt(x):
            return "n/a" if x is None else str(x)

        from_avail = None if (avail is None or first is None) else max(first - avail, 0)
        print(f"| {ds.name} | {fmt(delay.onset_frame)} | {fmt(avail)} | {fmt(first)} | "
              f"{fmt(delay.frames)} | {fmt(from_avail)} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
