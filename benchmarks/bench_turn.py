"""Rotation error over a turn in place (issue 12: below 1° over a 360° yaw turn).

    python benchmarks/bench_turn.py DATASET [DATASET ...] [--config FILE]

Per dataset the VO runs in-process (as ``granite run``, sequential mode; the concurrent mode
gives the same trajectory) and the table gives the longest turn in place of the ground truth
(:func:`granite.evaluation.turn.turn_rotation_error`: consecutive frames each turning by more
than 0.05° while moving at most 5 mm), the true rotation along it and the largest error of the
estimated rotation since the turn's first frame. E.g. ``granite-sim render panorama --out
runs/panorama`` (a 360° yaw at 8 m) then ``python benchmarks/bench_turn.py runs/panorama``.
Ground truth is required.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _vo_datasets import parse_config_and_datasets  # noqa: E402


def main(argv=None) -> int:
    parsed = parse_config_and_datasets(__doc__.splitlines()[0], argv)
    if parsed is None:
        return 2
    config, datasets = parsed
    from granite.estimator.runner import run_vo
    from granite.evaluation.turn import turn_rotation_error

    print("| dataset | turn (estimate frames) | true rotation deg | max rotation error deg | restarts |")
    print("| --- | --- | ---: | ---: | ---: |")
    for ds in datasets:
        result = run_vo(ds, config, progress=False, concurrent=False)
        turn = turn_rotation_error(result.trajectory, ds.ground_truth)
        restarts = result.restarts
        if turn is None:
            print(f"| {ds.name} | no turn in place | | | {restarts} |", flush=True)
            continue
        print(f"| {ds.name} | {turn.first}-{turn.last} | {turn.turned_deg:.1f} | "
              f"{turn.max_deg:.3f} | {restarts} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
