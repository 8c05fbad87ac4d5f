"""Shared command line of the benchmarks that run the VO on datasets with ground truth
(``bench_init.py``, ``bench_turn.py``): positional DATASET folders and ``--config FILE``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def parse_config_and_datasets(description: str, argv=None):
    """``(config, datasets)`` from the command line, or None after printing a one-line error
    (unreadable configuration, missing dataset, no ground truth): the caller exits with 2."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("datasets", nargs="+", type=Path)
    ap.add_argument("--config", type=Path, default=None, help="VO configuration (TOML)")
    args = ap.parse_args(argv)

    from granite.errors import GraniteError
    from granite.estimator.config import VoConfig
    from granite.io import open_dataset

    try:
        config = VoConfig.load(args.config) if args.config else VoConfig()
        datasets = [open_dataset(p) for p in args.datasets]
    except GraniteError as error:
        print(f"error: {error}", file=sys.stderr)
        return None
    for ds in datasets:
        if ds.ground_truth is None:
            print(f"error: {ds.root}: no ground truth", file=sys.stderr)
            return None
    return config, datasets
