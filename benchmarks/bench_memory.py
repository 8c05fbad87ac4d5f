"""Where the memory of a ``granite run`` goes (issue 15): resident memory per stage, and the
arrays the VO holds at its largest resident size.

Runs what ``granite run DATASET --out DIR [--rerun FILE]`` runs, in this process. Prints per
stage the resident size at its end and its peak (the kernel's high-water mark ``VmHWM``, reset
at every stage: what ``/usr/bin/time`` reports for the whole run), the increment over the
previous stage, and
for the VO stage the numpy arrays reachable from the estimator (grouped by component: optical
flow, sliding window, ...) at the sampled frame with the largest resident size. What the
arrays do not explain is the allocator's slack, numba's runtime allocations (typed
containers, temporaries) and the libraries' own buffers.

    python benchmarks/bench_memory.py DATASET [--max-frames N] [--sequential] [--rerun]

Linux only (``/proc``). Run it with a warm numba cache (one ``granite run`` before): a cold
cache compiles the kernels in this process and its peak is the compiler's.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import weakref
from pathlib import Path

import numpy as np


def _status_mb(key: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    raise RuntimeError(f"no {key} in /proc/self/status")


def rss_mb() -> float:
    """Resident set size of this process in MB (``VmRSS``)."""
    return _status_mb("VmRSS")


class StagePeaks:
    """Per-stage high-water marks of the resident size: ``stage(name)`` reads the peak since
    the last stage (``VmHWM``) and resets it (``5`` into ``/proc/self/clear_refs``, Linux 4.0+),
    so every short spike counts, as in ``/usr/bin/time``'s maximum resident size."""

    def __init__(self):
        self.stages: list[tuple[str, float, float]] = []  # (name, end RSS, peak RSS)
        self._name = "start"
        self._reset()

    @staticmethod
    def _reset() -> None:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")

    def stage(self, name: str) -> None:
        """Close the running stage and start ``name``."""
        self.stages.append((self._name, rss_mb(), _status_mb("VmHWM")))
        self._name = name
        self._reset()

    def close(self) -> None:
        self.stage("")


def array_bytes(root, seen: set[int], depth: int = 0) -> int:
    """Bytes of the numpy arrays reachable from ``root`` (attributes, containers) not in ``seen``.

    Views count their base once. Modules, classes and functions are not followed."""
    if depth > 12 or id(root) in seen:
        return 0
    seen.add(id(root))
    if isinstance(root, np.ndarray):
        base = root
        while isinstance(base.base, np.ndarray):
            base = base.base
        if base is not root:
            return array_bytes(base, seen, depth + 1)
        return int(root.nbytes) if root.flags.owndata else 0
    if isinstance(root, (str, bytes, int, float, bool, type(None), type, type(rss_mb))):
        return 0
    if type(root).__module__ in ("builtins",) and not isinstance(root, (dict, list, tuple, set)):
        return 0
    total = 0
    if isinstance(root, dict):
        for key, value in root.items():
            total += array_bytes(key, seen, depth + 1) + array_bytes(value, seen, depth + 1)
        return total
    if isinstance(root, (list, tuple, set, frozenset)):
        for value in root:
            total += array_bytes(value, seen, depth + 1)
        return total
    members = getattr(root, "__dict__", None)
    if members is not None:
        total += array_bytes(members, seen, depth + 1)
    for slot in getattr(type(root), "__slots__", ()):
        if hasattr(root, slot):
            total += array_bytes(getattr(root, slot), seen, depth + 1)
    return total


def component_bytes(vo) -> dict[str, int]:
    """Array bytes per attribute of the estimator, largest first (shared arrays count once,
    for the component walked first: the optical flow, then the window, then the rest)."""
    seen: set[int] = set()
    order = ["flow", "window", "refinder", "triangulator", "selector", "_tracks"]
    names = order + sorted(k for k in vars(vo) if k not in order)
    sizes = {}
    for name in names:
        if not hasattr(vo, name):
            continue
        part = getattr(vo, name)
        inner = vars(part) if hasattr(part, "__dict__") else {}
        for key in inner:  # one level down: flow.pyramids, window.landmarks, ...
            sizes[f"{name}.{key}"] = array_bytes(inner[key], seen)
        sizes[name] = array_bytes(part, seen)
    return dict(sorted(sizes.items(), key=lambda kv: -kv[1]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--sequential", action="store_true", help="granite run --sequential")
    parser.add_argument("--rerun", action="store_true", help="also write a rerun recording")
    parser.add_argument("--warmup", type=Path, default=None,
                        help="run the VO on this (small) dataset first and free it: the numba "
                             "kernels' share is then a stage of its own")
    parser.add_argument("--every", type=int, default=25, help="frames between array walks")
    args = parser.parse_args()

    sampler = StagePeaks()
    sampler.stage("import numpy, OpenCV, numba")
    import cv2  # noqa: F401
    import numba  # noqa: F401
    sampler.stage("import granite")
    from granite.cli.run_cmd import perform_run
    from granite.errors import GraniteError
    from granite.estimator import runner
    from granite.estimator.config import VoConfig
    from granite.io import open_dataset
    if args.warmup is not None:
        sampler.stage(f"warm-up run on {args.warmup.name}, freed (numba kernels)")
        runner.run_vo(open_dataset(args.warmup), VoConfig(), progress=False,
                      concurrent=not args.sequential)  # returns its freed memory
    sampler.stage("open the dataset")
    try:
        dataset = open_dataset(args.dataset)
    except GraniteError as error:
        print(f"bench_memory.py: error: {error}", file=sys.stderr)
        return 2
    config = VoConfig()

    captured: dict = {}
    original = runner.MonocularVO

    class CapturedVO(original):  # the run's estimator, for the array walk
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            captured["vo"] = weakref.ref(self)

    runner.MonocularVO = CapturedVO
    best = {"rss": 0.0, "frame": -1, "components": {}}
    frames = {"n": 0}
    original_run_vo = runner.run_vo

    def run_vo(*a, on_frame=None, **k):
        def hook(frame, output):
            frames["n"] += 1
            if frames["n"] == 1:
                sampler.stage("VO (frames 2 ..), its memory freed at the end")
            if frames["n"] % args.every == 0:
                value = rss_mb()
                if value > best["rss"]:
                    best.update(rss=value, frame=frame.index,
                                components=component_bytes(captured["vo"]()))
            if on_frame is not None:
                on_frame(frame, output)
        result = original_run_vo(*a, on_frame=hook, **k)
        sampler.stage("evaluation, run folder")
        return result

    import granite.cli.run_cmd as run_cmd
    original_report = run_cmd.write_run_report

    def write_run_report(*a, **k):
        sampler.stage("report and plots (matplotlib)")
        return original_report(*a, **k)

    run_cmd.run_vo = run_vo
    run_cmd.write_run_report = write_run_report
    sampler.stage("first frame (numba kernels from the cache"
                  + ("; rerun)" if args.rerun else ")"))
    with tempfile.TemporaryDirectory() as tmp:
        rrd = Path(tmp) / "run.rrd" if args.rerun else None
        perform_run(dataset, config, Path(tmp) / "run", rrd, False, 1.0, progress=False,
                    concurrent=not args.sequential, max_frames=args.max_frames)
    sampler.close()

    print(f"granite run {args.dataset} ({frames['n']} frames, "
          f"{'sequential' if args.sequential else 'concurrent'}{', rerun' if args.rerun else ''})")
    print(f"{'stage':52s} {'end MB':>8s} {'peak MB':>8s} {'+MB':>7s}")
    previous = None
    for name, end, peak in sampler.stages:
        if not name:
            continue
        grow = "" if previous is None else f"{end - previous:+7.0f}"
        print(f"{name:52s} {end:8.0f} {peak:8.0f} {grow:>7s}")
        previous = end
    peak = max(p for _, _, p in sampler.stages)
    print(f"peak resident size {peak:.0f} MB")
    if best["frame"] >= 0:
        total = sum(best["components"].values())
        print(f"arrays held by the estimator at frame {best['frame']} "
              f"(resident {best['rss']:.0f} MB): {total / 2**20:.1f} MB")
        for name, size in best["components"].items():
            if size >= 2**16:
                print(f"  {name:30s} {size / 2**20:7.1f} MB")
    print(numba_libraries_line())
    return 0


def numba_libraries_line() -> str:
    """One line on numba's code libraries in this process: how many were loaded from the
    cache or compiled here, and the LLVM bitcode kept for linking instead of parsed IR
    (granite/_numba_linking.py)."""
    import gc

    from numba.core import codegen

    from granite import _numba_linking

    libraries = [o for o in gc.get_objects() if type(o) is codegen.JITCodeLibrary]
    kept = [o.__dict__.get(_numba_linking._BITCODE) for o in libraries]
    loaded = sum(bool(o._disable_inspection) for o in libraries)  # set by a load from the cache
    parsed = sum(o._shared_module is not None for o in libraries)
    patched = getattr(codegen.CPUCodeLibrary, _numba_linking._MARK, False)
    return (f"numba: {len(libraries)} code libraries ({loaded} from the cache, "
            f"{len(libraries) - loaded} compiled here), {sum(len(b) for b in kept if b) / 2**20:.1f} MB "
            f"of bitcode kept for linking, {parsed} with parsed IR "
            f"(lazy linking IR {'on' if patched else 'off'})")


if __name__ == "__main__":
    sys.exit(main())
