"""rerun views of datasets, frontend tracks and VO runs (see the README's entity layout)."""

from granite.visualization.colors import INFINITY_COLOR, UNMAPPED_COLOR, inverse_distance_colors
from granite.visualization.rerun_logger import RerunLogger

__all__ = ["INFINITY_COLOR", "UNMAPPED_COLOR", "RerunLogger", "inverse_distance_colors"]
