"""The host's CPU accounting over a timed run (Linux ``/proc/stat``), for the speed benchmarks.

On a virtual machine the hypervisor may run other guests on the physical cores behind our
virtual CPUs: that time is *steal* (the ``steal`` column of ``/proc/stat``: the virtual CPU
was ready to run but the host did not run it). On this project's 2-core VM steal was 0-40 % of
the CPU time during concurrent VO runs minutes apart (twenty-fourth session, docs/architecture.md),
part of why the same code ran 20-40 % slower or faster from one run to the next (other slow
minutes showed system time instead, no steal). The benchmarks print it beside every timing so
that a reader can tell a slow host from slow code.
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
