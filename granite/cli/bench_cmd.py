"""``granite bench``: a study (scenarios x terrain seeds x VO variants) on a Dask cluster."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from granite.cli.run_cmd import positive_int
from granite.errors import ConfigError

DESCRIPTION = """\
Run a study: render every scenario x terrain seed of the STUDY file (frame ranges as separate
tasks; Blender in a subprocess per task), run the VO with every variant on every sequence,
evaluate every run and write into OUT:

  results.csv       one row per sequence x variant: restarts, tracking %, initialisation
                    delay, RMS RPE, ATE / path, Λ_scaledrift figures, VO fps and wall time
                    (vo_fps and vo_wall_s are timing: they differ between runs)
  report.md         paper-style tables (Table I failures, Table II RPE, per sequence and
                    variant, with totals and means) and the plots
  metrics.png, trajectories/<sequence>.png
  sequences/, scenarios/   the rendered sequences and the scenario files they come from
  runs/<sequence>/<variant>/   every run folder (as granite run writes it)

The tasks run on Dask: by default a LocalCluster on this machine (one single-threaded worker
process per core, listening on 127.0.0.1 only); --workers N sizes it, --scheduler ADDRESS uses
an existing cluster (every worker must see OUT and this package at the same paths), --serial
runs everything in this process without Dask. Running the same command again resumes: finished
renders, runs and evaluations are kept and only the missing work is submitted. Bundled studies:
studies/assets_smoke.toml (VO only on assets/sequences, under a minute), studies/paper_tables.toml.
The file format and the cluster set-ups (dask scheduler / dask worker by hand, SLURM or PBS
with dask-jobqueue, Kubernetes, TLS): docs/bench.md. Never expose a scheduler port without TLS:
a Dask scheduler runs whatever a client sends it.
"""


def dashboard_address(text: str) -> str:
    """argparse type: ``HOST:PORT`` or ``:PORT`` (all interfaces), the port an integer 0-65535
    (0: any free port)."""
    host, colon, port = text.rpartition(":")
    if not colon:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT or :PORT, got {text!r}")
    try:
        number = int(port)
    except ValueError:
        number = -1
    if not 0 <= number <= 65535:
        raise argparse.ArgumentTypeError(f"the port must be an integer 0-65535, got {port!r} in {text!r}")
    return text


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("bench", help="run a study on a Dask cluster (paper tables)",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("study", help="study file (TOML) or bundled study name (studies/NAME.toml)")
    p.add_argument("--out", type=Path, required=True, help="study folder to write (resumable)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="address of a running Dask scheduler, e.g. tcp://127.0.0.1:8786 or tls://host:8786")
    where.add_argument("--workers", type=positive_int, metavar="N",
                       help="worker processes of the local cluster (default: one per core)")
    where.add_argument("--serial", action="store_true", help="no Dask: every task in this process, in order")
    p.add_argument("--dashboard-address", type=dashboard_address, default="127.0.0.1:8787", metavar="HOST:PORT",
                   help="dashboard of the local cluster (default 127.0.0.1:8787; a free port if taken)")
    p.add_argument("--tls-ca-file", type=Path, help="TLS: CA certificate (PEM) for --scheduler tls://...")
    p.add_argument("--tls-cert", type=Path, help="TLS: this client's certificate (PEM)")
    p.add_argument("--tls-key", type=Path, help="TLS: this client's private key (PEM)")
    p.add_argument("--dry-run", action="store_true", help="validate and list the tasks still to run, run nothing")
    return p


def _security(args):
    given = [x for x in (args.tls_ca_file, args.tls_cert, args.tls_key) if x is not None]
    if not given:
        return None
    if len(given) != 3:
        raise ConfigError("TLS needs all of --tls-ca-file, --tls-cert and --tls-key")
    for path in given:
        if not path.is_file():
            raise ConfigError(f"{path}: TLS file not found")
    if not (args.scheduler or "").startswith("tls://"):
        raise ConfigError("the TLS options are for --scheduler tls://HOST:PORT")
    from distributed.security import Security

    return Security(tls_ca_file=str(args.tls_ca_file), tls_client_cert=str(args.tls_cert),
                    tls_client_key=str(args.tls_key), require_encryption=True)


def execute(study, out: Path, scheduler: str | None = None, workers: int | None = None, serial: bool = False,
            dashboard_address: str = "127.0.0.1:8787", security=None):
    """Run a validated study: serially, on the scheduler at ``scheduler``, or on a LocalCluster
    of ``workers`` processes (default: one per core). Returns (rows, failed tasks)."""
    from granite.bench.execute import local_cluster, run_study

    if serial:
        return run_study(study, out)
    from distributed import Client

    if scheduler:
        cluster = None
        if scheduler.startswith("tls://") and security is None:
            raise ConfigError(f"{scheduler}: a tls:// scheduler needs --tls-ca-file, --tls-cert and --tls-key")
        try:
            client = Client(scheduler, security=security)  # timeout: distributed.comm.timeouts.connect
        except (OSError, TimeoutError, ValueError, TypeError) as error:
            raise ConfigError(f"cannot connect to the scheduler {scheduler}: {error}") from None
        print(f"scheduler {scheduler}: {len(client.scheduler_info().get('workers', {}))} workers; "
              f"dashboard {client.dashboard_link}", flush=True)
    else:
        try:
            cluster = local_cluster(workers, dashboard_address)
        except (RuntimeError, OSError, ValueError) as error:
            reason = str(error).strip().splitlines()[-1] if str(error).strip() else type(error).__name__
            raise ConfigError(f"the local Dask cluster failed to start (dashboard {dashboard_address}): "
                              f"{reason}") from None
        client = Client(cluster)
        print(f"local cluster {cluster.scheduler_address}: {len(cluster.workers)} worker processes "
              f"on 127.0.0.1; dashboard {client.dashboard_link}", flush=True)
    try:
        return run_study(study, out, client)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def run(args) -> int:
    from granite.bench.execute import plan_study
    from granite.bench.study import check_existing_sequences, load_study
    from granite.io import check_writable

    study = load_study(args.study)
    check_writable(args.out)
    check_existing_sequences(study, args.out)
    security = _security(args)
    if args.dry_run:
        plan = plan_study(study, args.out)
        print(f"{study.name}: {len(study.sequences)} sequences x {len(study.variants)} variants = "
              f"{len(study.runs())} runs; {len(plan.tasks)} tasks to run "
              f"(finished and kept: {plan.kept})")
        for task in plan.tasks:
            after = f"  after {', '.join(d.rsplit('-', 1)[0] for d in task.deps)}" if task.deps else ""
            print(f"  {task.kind:<8} {task.what}{after}")
        return 0
    rows, failed = execute(study, args.out, args.scheduler, args.workers, args.serial,
                           args.dashboard_address, security)
    ok = sum(1 for r in rows if r.get("status") == "ok")
    print(f"{ok} of {len(rows)} runs evaluated; results: {args.out / 'results.csv'}, "
          f"report: {args.out / 'report.md'}")
    if failed:
        print(f"granite bench: {len(failed)} task(s) failed (see FAILED above); running the same "
              "command again retries them", file=sys.stderr)
        return 1
    return 0
