"""Robustness metrics from the sub-map indices of an estimate (paper Fig. 7, Table I).

A *run* is a maximal block of consecutive poses with the same sub-map index, i.e. one
continuously tracked section; a new run starts after every tracking failure.
"""

from __future__ import annotations

from granite.trajectory import Trajectory


def longest_run_duration(est: Trajectory) -> float:
    """Time from the first to the last pose of the longest sub-map run, in seconds."""
    ts = est.timestamps
    return max((float(ts[b - 1] - ts[a]) for a, b in est.runs()), default=0.0)


def tracking_percentage(est: Trajectory, span: tuple[float, float] | None = None) -> float:
    """Longest continuously tracked section divided by the sequence duration, in percent.

    The sequence duration is ``span[1] - span[0]`` when given (e.g. first and last frame of
    the dataset), else the estimate's first to last timestamp. A trajectory without sub-map
    indices is one run (100 %). A zero duration gives 100 % for a non-empty estimate.
    """
    if len(est) == 0:
        return 0.0
    duration = est.duration if span is None else float(span[1] - span[0])
    if duration <= 0:
        return 100.0
    return 100.0 * min(longest_run_duration(est) / duration, 1.0)


def restart_count(est: Trajectory) -> int:
    """Number of sub-map changes along time (tracking failures followed by a restart)."""
    return max(len(est.runs()) - 1, 0)
