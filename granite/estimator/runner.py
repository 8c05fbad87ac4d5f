"""Run the VO over a dataset and write the run folder.

Run folder (all files written atomically when the run ends or is interrupted):

=====================  ================================================================
``trajectory.tum``     ``T_w_c`` of every estimated frame, plain 8-column TUM text (evo reads
                       it as written); skipped frames are left out
``submaps.csv``        ``timestamp,frame_index,submap``: one row per ``trajectory.tum`` pose
``trajectory.kitti``   with ``--format kitti``: the same poses as KITTI odometry rows
``diagnostics.csv``    one row per frame, skipped ones included (see
                       :mod:`granite.estimator.diagnostics`)
``keyframes.csv``      ``timestamp,frame_index,submap`` of every keyframe
``landmarks.npz``      per-frame tracks, window landmarks and keyframes for ``granite view``
                       (see :mod:`granite.estimator.records`)
``config.toml``        the exact configuration used
``summary.json``       frame counts, skipped frames, restarts, warnings by kind, timing
=====================  ================================================================

Warnings raised while a frame is processed are recorded, never silenced: each kind (category
and source line) is shown once, as a warning, and counted per frame (``warnings`` column) and
per kind (``summary.json``).
"""

from __future__ import annotations

import ctypes
import gc
import json
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from granite._numba_cache import compile_notice
from granite.errors import InputError
from granite.estimator.config import VoConfig
from granite.estimator.diagnostics import FrameDiagnostics, write_diagnostics
from granite.estimator.pipeline import VoPipeline
from granite.estimator.vo import MonocularVO
from granite.io import Dataset, atomic_write_text, write_kitti_poses, write_tum
from granite.optical_flow.frame_to_frame import FrameRejectedWarning
from granite.trajectory import Trajectory

#: Trajectory formats ``granite run --format`` writes besides ``trajectory.tum``.
TRAJECTORY_FORMATS = ("tum", "kitti")


class RunWarning(UserWarning):
    """The first occurrence of a kind of problem met during a run (the rest are counted)."""


@dataclass
class WarningKind:
    """One kind of warning of a run: ``count`` occurrences, the first in ``first_frame``."""

    kind: str  # "skipped", "frontend rejection" or the warning category (e.g. RuntimeWarning)
    message: str
    where: str  # source "file:line" of a Python warning, else ""
    first_frame: int
    count: int = 0

    def to_dict(self) -> dict:
        return {"kind": self.kind, "message": self.message, "where": self.where,
                "first_frame": self.first_frame, "count": self.count}


class WarningTally:
    """Counts warnings by kind and shows the first of each: ``notify(text)``, or by default a
    :class:`RunWarning`."""

    def __init__(self, notify=None) -> None:
        self.kinds: dict[tuple, WarningKind] = {}
        self.notify = notify

    def add(self, key: tuple, kind: str, message: str, where: str, frame_index: int, show: str) -> None:
        entry = self.kinds.get(key)
        if entry is None:
            entry = self.kinds[key] = WarningKind(kind, message, where, frame_index)
            text = f"{show} (shown once; every occurrence is counted in summary.json)"
            if self.notify is not None:
                self.notify(text)
            else:
                warnings.warn(text, RunWarning, stacklevel=3)
        entry.count += 1

    def add_python_warning(self, record: warnings.WarningMessage, frame_index: int) -> None:
        where = f"{record.filename}:{record.lineno}"
        name = record.category.__name__
        self.add((name, record.filename, record.lineno), name, str(record.message), where, frame_index,
                 f"frame {frame_index}: {name}: {record.message} ({where})")

    def counts(self, kind: str) -> dict[str, int]:
        """Occurrences per message of one kind."""
        out: dict[str, int] = {}
        for entry in self.kinds.values():
            if entry.kind == kind:
                out[entry.message] = out.get(entry.message, 0) + entry.count
        return out

    def numerical(self) -> list[WarningKind]:
        """The Python warnings (numerical and others), frontend rejections excluded."""
        return [k for k in self.kinds.values() if k.kind not in ("skipped", "frontend rejection")]


@dataclass
class RunResult:
    """What a run produced. ``trajectory`` holds the estimated frames only (skipped frames have
    no pose); ``diagnostics`` one row per processed frame, skipped ones included."""

    trajectory: Trajectory
    diagnostics: list[FrameDiagnostics]
    keyframes: list[tuple[float, int, int]]
    skipped: list[tuple[int, str]] = field(default_factory=list)
    interrupted: bool = False
    #: dataset frame index of every trajectory pose.
    frame_indices: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    tally: WarningTally = field(default_factory=WarningTally)
    #: why the evaluation against the ground truth failed (set by the caller), else None.
    evaluation_error: str | None = None
    #: wall time spent writing the rerun recording (one-time startup, frames + 3D content).
    logging_startup_seconds: float = 0.0
    logging_seconds: float = 0.0

    @property
    def restarts(self) -> int:
        sub = self.trajectory.submap
        return 0 if sub is None or len(sub) == 0 else int(np.count_nonzero(np.diff(sub)))


def check_dataset(dataset: Dataset) -> None:
    """Fail early, with one clear line, on what would stop a run."""
    if len(dataset) == 0:
        raise InputError("the dataset has no images", dataset.root)
    if dataset.calibration is None:
        why = "; ".join(dataset.notes) or "no calib.json found"
        raise InputError(f"no usable camera calibration ({why}); pass --calib calib.json", dataset.root)
    calib = dataset.calibration
    first = next((f for f in dataset.frames() if f.image is not None), None)
    if first is None:
        raise InputError("no image of the dataset could be read", dataset.root)
    h, w = first.image.shape[:2]
    if (w, h) != (calib.width, calib.height):
        raise InputError(
            f"image size {w}x{h} does not match the calibration's {calib.width}x{calib.height}",
            first.path,
        )


def _largest_kernels() -> tuple:
    """The VO's kernels that take longest to compile: when numba has not cached them, the run
    starts with the compilation (:func:`granite._numba_cache.compile_notice`)."""
    from granite.backend.reprojection import linearize_fused
    from granite.backend.schur import schur_reduce
    from granite.optical_flow import tracking

    return (schur_reduce, tracking._track_passes_claimed, tracking._track_passes, linearize_fused)


def run_vo(
    dataset: Dataset,
    config: VoConfig,
    progress: bool = True,
    on_frame=None,
    max_frames: int | None = None,
    notify=None,
    concurrent: bool = True,
) -> RunResult:
    """Process the dataset frame by frame. ``on_frame(frame, output)`` is called after each
    frame (used by the rerun logger); ``notify(text)`` shows the first warning of each kind
    (default: a :class:`RunWarning`). Ctrl-C stops early and returns what was processed.
    ``concurrent``: the frontend of the next frame runs while the estimator works on this one
    (:mod:`granite.estimator.pipeline`; bit-identical results), else one frame after the
    other (``granite run --sequential``)."""
    check_dataset(dataset)
    camera = dataset.calibration.camera()
    vo = MonocularVO(camera, config)
    vo.export_landmarks = True  # window landmarks go into the run records
    times, poses, submaps, indices, diags, skipped = [], [], [], [], [], []
    interrupted = False
    n = len(dataset) if max_frames is None else min(max_frames, len(dataset))
    bar = tqdm(total=n, desc=f"granite run {dataset.name}", unit="frame", disable=not progress)
    if progress and (notice := compile_notice("granite run", _largest_kernels())):
        bar.write(notice, file=sys.stderr)
    tally = WarningTally(notify)
    pipeline = VoPipeline(vo, concurrent)
    outputs = pipeline.run(dataset.frames(0, n))

    def record_frame(frame, out, caught) -> None:
        numerical = 0
        for record in caught:
            if issubclass(record.category, FrameRejectedWarning):
                continue  # counted below, by reason
            tally.add_python_warning(record, frame.index)
            numerical += 1
        diag = out.diagnostics
        diag.warnings = numerical
        if frame.image is None:
            reason = frame.error or "unreadable"
            skipped.append((frame.index, reason))
            tally.add(("skipped", reason), "skipped", reason, "", frame.index,
                      f"frame {frame.index} skipped: {reason} ({frame.path})")
        elif diag.state == "skipped":
            reason = (out.tracks.rejected if out.tracks is not None else None) or "rejected"
            skipped.append((frame.index, reason))
            tally.add(("frontend rejection", reason), "frontend rejection", reason, "", frame.index,
                      f"frame {frame.index} skipped: the frontend rejected it ({reason})")
        else:
            times.append(frame.timestamp)
            poses.append(out.T_w_c)
            submaps.append(diag.submap)
            indices.append(frame.index)
        diags.append(diag)
        if on_frame is not None:
            on_frame(frame, out)
        bar.update(1)
        bar.set_postfix(state=diag.state, submap=diag.submap, refresh=False)

    try:
        while True:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                item = next(outputs, None)
            if item is None:
                break
            record_frame(*item, caught)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        outputs.close()
        if interrupted:  # the frame finished but not yet handed out (its Λ was computing)
            for frame, out, caught in pipeline.drain():
                record_frame(frame, out, caught)
        bar.close()
    if not diags:
        raise InputError("no frame was processed", dataset.root)
    if not times:
        raise InputError("no frame could be estimated: every processed frame was skipped", dataset.root)
    keyframes = [(float(dataset.timestamps[f]), f, s) for f, s in vo.keyframe_log if f < len(dataset)]
    traj = Trajectory(np.array(times), np.array(poses), np.array(submaps, dtype=np.int64))
    del vo, pipeline, outputs
    return_freed_memory()
    return RunResult(traj, diags, keyframes, skipped, interrupted, np.array(indices, np.int64), tally)


def return_freed_memory() -> None:
    """Free unreachable objects and hand the C heap's free pages back to the system.

    glibc's malloc keeps freed memory in the process (the numpy temporaries of thousands of
    frames leave the heap fragmented), so without this a run's resident size after the VO is
    its peak, and the report's plots come on top of it (docs/architecture.md, "Memory").
    No-op where the C library has no ``malloc_trim``."""
    gc.collect()
    try:
        ctypes.CDLL(None).malloc_trim(0)
    except (AttributeError, OSError, TypeError):  # no glibc (TypeError: Windows' CDLL(None))
        pass


def submaps_csv(result: RunResult) -> str:
    """``submaps.csv``: ``timestamp,frame_index,submap`` of every trajectory pose."""
    t, sub = result.trajectory.timestamps, result.trajectory.submap_ids()
    rows = ["timestamp,frame_index,submap"]
    rows += [f"{t[k]:.9f},{int(result.frame_indices[k])},{int(sub[k])}" for k in range(len(t))]
    return "\n".join(rows) + "\n"


def summary_dict(result: RunResult, extra: dict | None = None) -> dict:
    """The content of ``summary.json``."""
    ms = np.array([d.processing_ms for d in result.diagnostics])
    estimated = [d for d in result.diagnostics if d.state != "skipped"]
    mean_ms = float(np.mean([d.processing_ms for d in estimated])) if estimated else float(ms.mean())
    return {
        "frames": len(result.diagnostics),
        "estimated_frames": len(result.trajectory),
        "skipped_frames": len(result.skipped),
        "skipped": [{"frame_index": i, "reason": r} for i, r in result.skipped],
        "skipped_by_reason": result.tally.counts("skipped"),
        "frontend_rejections": result.tally.counts("frontend rejection"),
        "warnings": [k.to_dict() for k in result.tally.numerical()],
        "warning_count": sum(k.count for k in result.tally.numerical()),
        "restarts": result.restarts,
        "submaps": len(np.unique(result.trajectory.submap_ids())),
        "keyframes": len(result.keyframes),
        "mean_processing_ms": mean_ms,
        "frames_per_second": float(1000.0 / mean_ms) if mean_ms > 0 else None,
        "interrupted": result.interrupted,
        **optimization_summary(result.diagnostics),
        **(extra or {}),
    }


def optimization_summary(diagnostics: list[FrameDiagnostics]) -> dict:
    """What ``summary.json`` says of Gauss-Newton and of Λ_scaledrift, from the diagnostics:
    ``gn_mean_iterations`` and ``gn_unconverged_frames`` over the frames whose main
    optimisation ran, ``scale_drift_defined_frames`` and ``scale_drift_no_scale_frames`` (Λ
    found no scale information: no anchor, or a keyframe link that carries none)."""
    optimized = [d for d in diagnostics if d.gn_converged is not None]
    return {
        "gn_mean_iterations": (float(np.mean([d.gn_iterations for d in optimized]))
                               if optimized else None),
        "gn_unconverged_frames": sum(1 for d in optimized if not d.gn_converged),
        "gn_optimized_frames": len(optimized),
        "scale_drift_defined_frames": sum(1 for d in diagnostics if d.scale_drift_indicator is not None),
        "scale_drift_no_scale_frames": sum(1 for d in diagnostics if d.no_scale_information),
    }


def write_run(out_dir: str | Path, result: RunResult, config: VoConfig, extra: dict | None = None,
              formats: tuple[str, ...] = ("tum",)) -> None:
    """Write the run folder (see the module docstring); ``formats`` from
    :data:`TRAJECTORY_FORMATS` (``trajectory.tum`` is always written)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_tum(out / "trajectory.tum", result.trajectory, submap_column=False)
    atomic_write_text(out / "submaps.csv", submaps_csv(result))
    if "kitti" in formats:
        write_kitti_poses(out / "trajectory.kitti", result.trajectory)
    else:  # not from an earlier run into the same folder
        (out / "trajectory.kitti").unlink(missing_ok=True)
    write_diagnostics(out / "diagnostics.csv", result.diagnostics)
    rows = ["timestamp,frame_index,submap"] + [f"{t:.9f},{f},{s}" for t, f, s in result.keyframes]
    atomic_write_text(out / "keyframes.csv", "\n".join(rows) + "\n")
    atomic_write_text(out / "config.toml", config.to_toml())
    atomic_write_text(out / "summary.json", json.dumps(summary_dict(result, extra), indent=2) + "\n")
