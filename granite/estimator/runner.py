"""Run the VO over a dataset and write the run folder.

Run folder (all files written atomically when the run ends or is interrupted):

=====================  ================================================================
``trajectory.tum``     pose ``T_w_c`` of every processed frame, TUM text with a 9th column,
                       the sub-map index (skipped frames repeat the last pose)
``diagnostics.csv``    one row per frame (see :mod:`granite.estimator.diagnostics`)
``keyframes.csv``      ``timestamp,frame_index,submap`` of every keyframe
``landmarks.npz``      per-frame tracks, window landmarks and keyframes for ``granite view``
                       (see :mod:`granite.estimator.records`)
``config.toml``        the exact configuration used
``summary.json``       frame counts, skipped frames, restarts, timing
=====================  ================================================================
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from granite.errors import InputError
from granite.estimator.config import VoConfig
from granite.estimator.diagnostics import FrameDiagnostics, write_diagnostics
from granite.estimator.vo import FrameOutput, MonocularVO
from granite.io import Dataset, atomic_write_text, write_tum
from granite.trajectory import Trajectory


@dataclass
class RunResult:
    trajectory: Trajectory
    diagnostics: list[FrameDiagnostics]
    keyframes: list[tuple[float, int, int]]
    skipped: list[tuple[int, str]] = field(default_factory=list)
    interrupted: bool = False
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


def run_vo(
    dataset: Dataset,
    config: VoConfig,
    progress: bool = True,
    on_frame=None,
    max_frames: int | None = None,
) -> RunResult:
    """Process the dataset frame by frame. ``on_frame(frame, output)`` is called after each
    frame (used by the rerun logger). Ctrl-C stops early and returns what was processed."""
    check_dataset(dataset)
    camera = dataset.calibration.camera()
    vo = MonocularVO(camera, config)
    vo.export_landmarks = True  # window landmarks go into the run records
    times, poses, submaps, diags, skipped = [], [], [], [], []
    interrupted = False
    n = len(dataset) if max_frames is None else min(max_frames, len(dataset))
    bar = tqdm(total=n, desc=f"granite run {dataset.name}", unit="frame", disable=not progress)
    try:
        for frame in dataset.frames(0, n):
            if frame.image is None:
                warnings.warn(f"{frame.path}: skipped ({frame.error})", stacklevel=2)
                skipped.append((frame.index, frame.error or "unreadable"))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # frontend rejections are counted as skipped
                out: FrameOutput = vo.process(frame.index, frame.timestamp, frame.image)
            if frame.image is not None and out.diagnostics.state == "skipped":
                skipped.append((frame.index, out.tracks.rejected if out.tracks else "rejected"))
            times.append(frame.timestamp)
            poses.append(out.T_w_c)
            submaps.append(out.diagnostics.submap)
            diags.append(out.diagnostics)
            if on_frame is not None:
                on_frame(frame, out)
            bar.update(1)
            bar.set_postfix(state=out.diagnostics.state, submap=out.diagnostics.submap, refresh=False)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        bar.close()
    if not times:
        raise InputError("no frame was processed", dataset.root)
    keyframes = [(float(dataset.timestamps[f]), f, s) for f, s in vo.keyframe_log if f < len(dataset)]
    traj = Trajectory(np.array(times), np.array(poses), np.array(submaps, dtype=np.int64))
    return RunResult(traj, diags, keyframes, skipped, interrupted)


def write_run(out_dir: str | Path, result: RunResult, config: VoConfig, extra: dict | None = None) -> None:
    """Write the run folder (see the module docstring)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_tum(out / "trajectory.tum", result.trajectory)
    write_diagnostics(out / "diagnostics.csv", result.diagnostics)
    rows = ["timestamp,frame_index,submap"] + [f"{t:.9f},{f},{s}" for t, f, s in result.keyframes]
    atomic_write_text(out / "keyframes.csv", "\n".join(rows) + "\n")
    atomic_write_text(out / "config.toml", config.to_toml())
    ms = np.array([d.processing_ms for d in result.diagnostics])
    summary = {
        "frames": len(result.diagnostics),
        "skipped_frames": len(result.skipped),
        "skipped": [{"frame_index": i, "reason": r} for i, r in result.skipped],
        "restarts": result.restarts,
        "keyframes": len(result.keyframes),
        "mean_processing_ms": float(ms.mean()),
        "frames_per_second": float(1000.0 / ms.mean()) if ms.mean() > 0 else None,
        "interrupted": result.interrupted,
        **(extra or {}),
    }
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
