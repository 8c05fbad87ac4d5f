"""Entry point of the ``granite`` command.

Subcommands are modules of :mod:`granite.cli` listed in :data:`SUBCOMMANDS`; each provides
``add_parser(subparsers) -> argparse.ArgumentParser`` and ``run(args) -> int``. User errors
(:class:`granite.errors.GraniteError`) and bad options are printed as one line on stderr with
exit status 2; Ctrl-C exits with 130.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence

# The VO's linear algebra works on small matrices, where BLAS threads only compete for cores.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from granite.errors import GraniteError  # noqa: E402

#: Subcommand modules, in the order ``--help`` lists them.
SUBCOMMANDS: tuple[str, ...] = ("demo", "run", "eval", "view", "track", "bench")


class OneLineErrorParser(argparse.ArgumentParser):
    """argparse with one-line errors: ``granite run: error: ... (see granite run --help)``
    (subcommand parsers inherit the class; granite-sim uses it too)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineErrorParser(
        prog="granite",
        description="Robust monocular visual odometry for flying robots (granite-py).",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in SUBCOMMANDS:
        module = importlib.import_module(f"granite.cli.{name}_cmd")
        sub = module.add_parser(subparsers)
        sub.set_defaults(run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except GraniteError as error:
        print(f"granite {args.command}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"granite {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
