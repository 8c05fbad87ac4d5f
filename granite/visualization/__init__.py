"""rerun views of datasets, frontend tracks and VO runs (see the README's entity layout), and the
run reports' plots (:mod:`granite.visualization.report`).

``RerunLogger`` is imported on first use: importing rerun (and pyarrow) costs about 44 MB of
resident memory, which a run without a recording (``granite run`` without ``--rerun``, its
report's plots) does not pay (docs/architecture.md, "Memory").
"""

from granite.visualization.colors import INFINITY_COLOR, UNMAPPED_COLOR, inverse_distance_colors

__all__ = ["INFINITY_COLOR", "UNMAPPED_COLOR", "RerunLogger", "inverse_distance_colors"]


def __getattr__(name: str):
    if name == "RerunLogger":
        from granite.visualization.rerun_logger import RerunLogger

        return RerunLogger
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
