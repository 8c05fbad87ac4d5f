"""The host's CPU accounting over a timed run (Linux ``/proc/stat``), for the speed benchmarks.

On a virtual machine the hypervisor may run other guests on the physical cores behind our
virtual CPUs: that time is *steal* (the ``steal`` column of ``/proc/stat``: the virtual CPU
was ready to run but the host did not run it). On this project's 2-core VM steal was 0-40 % of
the CPU time during concurrent VO runs minutes apart (twenty-fourth session, docs/architecture.md),
part of why the same code ran 20-40 % slower or faster from one run to the next (other slow
minutes showed system time instead, no steal). The benchmarks print it beside every timing so
that a reader can tell a slow host from slow code.

Steal did not explain every slow phase (twenty-fifth session: 49 against 61 frames/s on the
spiral an hour apart at 0-0.4 % steal), so the benchmarks also print :func:`speed_probe`: the
CPU time of a fixed piece of our own work (a linearisation and landmark elimination of a
seeded synthetic window), which changes only when the host's speed does.
"""

from __future__ import annotations

from pathlib import Path

#: Columns of the aggregate ``cpu`` line of ``/proc/stat`` (proc(5)), in order.
COLUMNS = ("user", "nice", "system", "idle", "iowait", "irq", "softirq", "steal")


def parse_cpu_line(text: str) -> dict[str, int] | None:
    """The aggregate ``cpu`` line of a ``/proc/stat`` text as ``{column: ticks}`` (the columns
    of :data:`COLUMNS`; guest time is already counted in user time), or None if there is none."""
    for line in text.splitlines():
        fields = line.split()
        if fields and fields[0] == "cpu":
            values = [int(v) for v in fields[1:1 + len(COLUMNS)]]
            values += [0] * (len(COLUMNS) - len(values))
            return dict(zip(COLUMNS, values))
    return None


def cpu_ticks(path: Path = Path("/proc/stat")) -> dict[str, int] | None:
    """The host's CPU ticks now, or None where ``/proc/stat`` cannot be read (not Linux)."""
    try:
        return parse_cpu_line(path.read_text())
    except OSError:
        return None


def shares(before: dict[str, int] | None, after: dict[str, int] | None) -> dict[str, float]:
    """Percent of all CPU ticks between two :func:`cpu_ticks` readings that were steal, idle
    and busy (user + nice + system + irq + softirq), over all CPUs; empty when either reading
    is missing or no tick passed."""
    if before is None or after is None:
        return {}
    delta = {k: after[k] - before[k] for k in COLUMNS}
    total = sum(delta.values())
    if total <= 0:
        return {}
    busy = sum(delta[k] for k in ("user", "nice", "system", "irq", "softirq"))
    return {"steal_pct": 100.0 * delta["steal"] / total,
            "idle_pct": 100.0 * (delta["idle"] + delta["iowait"]) / total,
            "busy_pct": 100.0 * busy / total}


def speed_probe(repeats: int = 100) -> dict[str, float]:
    """The host's speed at this moment on our own kind of work: the median thread CPU time
    (ms) of one linearisation + landmark Schur complement of a fixed synthetic window (14
    poses, 600 landmarks, about 3000 observations; the numba kernels of every Gauss-Newton
    step and of Λ_scaledrift), over ``repeats`` calls after a warm-up. The same code gives
    the same work, so a change of this figure between two benchmark runs is the host's, not
    the code's: the benchmarks print it beside their timings (``probe_ms``; lower = faster
    host). Also ``probe_spread``: (p90 - p10) / median of the calls."""
    import time

    import numpy as np

    work = probe_workload()
    work()  # warm-up: numba's cache, the workspace
    times = []
    for _ in range(max(int(repeats), 1)):
        t0 = time.thread_time()
        work()
        times.append(time.thread_time() - t0)
    ms = 1e3 * np.asarray(times)
    med = float(np.median(ms))
    return {"probe_ms": med,
            "probe_spread": float((np.percentile(ms, 90) - np.percentile(ms, 10)) / med)}


def probe_text(probe: dict[str, float]) -> str:
    """``host probe X.XX ms`` of :func:`speed_probe` for a benchmark's output."""
    return f"host probe {probe['probe_ms']:.2f} ms (spread {100 * probe['probe_spread']:.0f} %)"


def probe_workload():
    """The probe's fixed work: a callable that linearises a seeded synthetic window (14 poses,
    600 landmarks, about 3000 observations) and eliminates its landmarks, returning the
    reduced system (every call and every build the same)."""
    from granite.backend import BackendConfig
    from granite.backend.synthetic import build_window, make_scene

    scene = make_scene(num_frames=14, num_points=600, obs_per_landmark=6, recent_frames=3,
                       max_level=2, seed=0)
    window = build_window(scene, BackendConfig(), pose_noise=(0.01, 0.005),
                          bearing_noise=0.001, inv_dist_noise=0.1)
    problem = window.problem(None)
    cost = window.cost_terms()

    def work():
        return cost.linearize(problem)[1]

    work.num_observations = problem.packed.num_observations
    work.num_poses = len(problem.frame_ids)
    return work
