"""Command-line interface: ``granite <subcommand>``. Each subcommand lives in its own module
with ``add_parser(subparsers)`` (argument parsing) and ``run(args) -> int`` (the runner)."""
