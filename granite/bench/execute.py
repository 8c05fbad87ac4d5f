"""Executing a study: the task graph of the work still missing, run on a Dask cluster (a
``LocalCluster`` on 127.0.0.1 by default, or the scheduler at an address) or serially in this
process, with one progress line per finished task, then the aggregation."""

from __future__ import annotations

import os
import sys
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from granite.bench import report, tasks
from granite.bench.study import Study
from granite.io import atomic_write_text


@dataclass
class Task:
    key: str
    kind: str  # render, finalize, vo, evaluate
    what: str  # for the progress line
    fn: Callable
    args: tuple
    deps: list[str] = field(default_factory=list)
    run: tuple | None = None  # (sequence, variant) of vo / evaluate tasks


@dataclass
class Plan:
    tasks: list[Task]
    rows: dict  # (sequence id, variant name) -> row of a finished evaluation
    kept: dict  # kind -> number of finished tasks not submitted again


def plan_study(study: Study, out: Path) -> Plan:
    """The tasks still to do (finished renders, runs and evaluations are kept), in an order
    where every task comes after its dependencies."""
    out = Path(out)
    token = uuid.uuid4().hex[:8]
    todo: list[Task] = []
    kept = {"render": 0, "finalize": 0, "vo": 0, "evaluate": 0}
    rows: dict = {}
    ready: dict[str, str | None] = {}  # sequence id -> key of its finalize task (None = complete)
    for seq in study.sequences:
        ready[seq.id] = None
        if not seq.rendered or tasks.complete_marker(out, seq).is_file():
            if seq.rendered:
                kept["finalize"] += 1
                kept["render"] += len(seq.chunks(study.frames_per_task))
            continue
        keys = []
        for a, b in seq.chunks(study.frames_per_task):
            if tasks.render_marker(out, seq, a, b).is_file():
                kept["render"] += 1
                continue
            key = f"render-{seq.id}-{a}-{b}-{token}"
            todo.append(Task(key, "render", f"{seq.id} frames {a}:{b}", tasks.render_chunk, (out, seq, a, b)))
            keys.append(key)
        key = f"finalize-{seq.id}-{token}"
        todo.append(Task(key, "finalize", f"{seq.id}", tasks.finalize_sequence, (out, seq), keys))
        ready[seq.id] = key
    for seq, variant in study.runs():
        vo_key = None
        if ready[seq.id] is None and tasks.vo_done(out, seq, variant):
            kept["vo"] += 1
            row = tasks.read_row(out, seq, variant, study.delta, study.align)
            if row is not None:
                kept["evaluate"] += 1
                rows[(seq.id, variant.name)] = row
                continue
        else:
            vo_key = f"vo-{seq.id}-{variant.slug}-{token}"
            deps = [ready[seq.id]] if ready[seq.id] else []
            todo.append(Task(vo_key, "vo", f"{seq.id} / {variant.name}", tasks.run_vo,
                             (out, seq, variant, study.delta), deps, (seq, variant)))
        todo.append(Task(f"evaluate-{seq.id}-{variant.slug}-{token}", "evaluate", f"{seq.id} / {variant.name}",
                         tasks.evaluate_run, (out, seq, variant, study.delta, study.align),
                         [vo_key] if vo_key else [], (seq, variant)))
    return Plan(todo, rows, kept)


def _describe(task: Task, result, seconds: float | None) -> str:
    if task.kind == "evaluate" and isinstance(result, dict):
        r = result
        if r.get("status") != "ok":
            return f"{task.what}: {r.get('status')}"
        rpe = "n/a" if r["rpe_rmse"] is None else f"{r['rpe_rmse']:.3f} m"
        return (f"{task.what}: restarts {r['restarts']}, tracking {r['tracking_percentage']:.1f} %, "
                f"RPE {rpe}")
    took = f" ({result['seconds']:.1f} s)" if isinstance(result, dict) and "seconds" in result else ""
    return f"{task.what}{took}"


class Progress:
    """One line per finished task: ``[ 5/12 0:01:10] vo spiral_seed1... / ours (12.3 s)``."""

    def __init__(self, total: int, stream=None):
        self.total, self.done, self.t0 = total, 0, time.monotonic()
        self.stream = stream or sys.stdout

    def __call__(self, task: Task, result=None, error: BaseException | None = None) -> None:
        self.done += 1
        s = int(time.monotonic() - self.t0)
        stamp = f"[{self.done:>{len(str(self.total))}}/{self.total} {s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}]"
        text = f"FAILED: {task.what}: {type(error).__name__}: {error}" if error else _describe(task, result, None)
        text = text.splitlines()[0] if text else text
        if len(text) > 240:
            text = text[:237] + "..."
        print(f"{stamp} {task.kind:<8} {text}", file=self.stream, flush=True)


def _failed_row(task: Task, error: BaseException) -> dict:
    seq, variant = task.run
    row = tasks.base_row(seq, variant)
    row["status"] = f"{task.kind} failed: {type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}"
    return row


def _prepare_outputs(study: Study, out: Path) -> None:
    """Scenario files of the rendered sequences (the render tasks read them: DIR must be on a
    filesystem every worker sees)."""
    for seq in study.sequences:
        if seq.rendered:
            path = seq.scenario_file(out)
            if not path.is_file() or path.read_text(encoding="utf-8") != seq.scenario_text:
                atomic_write_text(path, seq.scenario_text)


def run_serial(plan: Plan, progress: Progress) -> tuple[list[dict], list[Task]]:
    """Every task in this process, in plan order."""
    results: dict[str, object] = {}
    failed: dict[str, BaseException] = {}
    rows, bad = [], []
    for task in plan.tasks:
        broken = next((failed[d] for d in task.deps if d in failed), None)
        try:
            if broken is not None:
                raise broken
            results[task.key] = task.fn(*task.args, *(results[d] for d in task.deps))
        except (KeyboardInterrupt, SystemExit):
            raise
        except Exception as error:  # noqa: BLE001 - a failed task is reported, the study goes on
            failed[task.key] = error
            bad.append(task)
            progress(task, error=error)
            if task.kind == "evaluate":
                rows.append(_failed_row(task, error))
            continue
        progress(task, results[task.key])
        if task.kind == "evaluate":
            rows.append(results[task.key])
    return rows, bad


def run_dask(plan: Plan, client, progress: Progress) -> tuple[list[dict], list[Task]]:
    """Submit the plan to a Dask client; results as they complete."""
    from distributed import as_completed

    futures = {}
    by_future = {}
    for task in plan.tasks:
        deps = [futures[d] for d in task.deps]
        # retries: a task that raised (e.g. Blender crashed) is tried once more; a task whose
        # worker died is rescheduled by the scheduler itself (distributed.scheduler.allowed-failures)
        fut = client.submit(task.fn, *task.args, *deps, key=task.key, pure=False, retries=1)
        futures[task.key] = fut
        by_future[fut.key] = task
    rows, bad = [], []
    for fut in as_completed(list(futures.values())):
        task = by_future[fut.key]
        if fut.status == "error" or fut.status == "cancelled":
            error = fut.exception() if fut.status == "error" else RuntimeError("cancelled")
            bad.append(task)
            progress(task, error=error)
            if task.kind == "evaluate":
                rows.append(_failed_row(task, error))
            continue
        result = fut.result()
        progress(task, result)
        if task.kind == "evaluate":
            rows.append(result)
    return rows, bad


def local_cluster(workers: int | None, dashboard_address: str = "127.0.0.1:8787"):
    """A LocalCluster of ``workers`` single-threaded worker processes (default: one per core)
    listening on 127.0.0.1 only."""
    import logging

    from distributed import LocalCluster

    n = workers or os.cpu_count() or 1
    return LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                        dashboard_address=dashboard_address, silence_logs=logging.ERROR)


def run_study(study: Study, out: Path, client=None, stream=None) -> tuple[list[dict], list[Task]]:
    """Plan, execute (``client``: a Dask client, or None for serial in this process) and
    aggregate. Returns (rows in table order, failed tasks)."""
    from granite.bench.study import check_existing_sequences

    out = Path(out).resolve()  # the tasks run elsewhere: absolute paths
    check_existing_sequences(study, out)
    out.mkdir(parents=True, exist_ok=True)
    stream = stream or sys.stdout
    _prepare_outputs(study, out)
    plan = plan_study(study, out)
    kept = ", ".join(f"{n} {k}" for k, n in plan.kept.items() if n)
    print(f"{study.name}: {len(study.sequences)} sequences x {len(study.variants)} variants; "
          f"{len(plan.tasks)} tasks to run" + (f" (finished and kept: {kept})" if kept else ""),
          file=stream, flush=True)
    progress = Progress(len(plan.tasks) + 1, stream)
    if client is None:
        rows, bad = run_serial(plan, progress)
    else:
        rows, bad = run_dask(plan, client, progress)
    rows = list(plan.rows.values()) + rows
    t0 = time.perf_counter()
    if client is None:
        result = report.aggregate(out, study, rows)
    else:
        result = client.submit(report.aggregate, out, study, rows, key=f"aggregate-{uuid.uuid4().hex[:8]}",
                               pure=False).result()
    result["seconds"] = time.perf_counter() - t0
    progress(Task("aggregate", "report", f"results.csv, report.md, {result['plots']} plots in {out}",
                  None, ()), result)
    order = {(s.id, v.name): i for i, (s, v) in enumerate(study.runs())}
    rows.sort(key=lambda r: order.get((r["sequence"], r["variant"]), len(order)))
    return rows, bad
