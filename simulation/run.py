"""One rendering run: validate everything (pure numpy), then build the world in Blender and
render the requested frames into a resumable output folder (:mod:`simulation.writer`)."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from granite.errors import ConfigError
from simulation.plan import RunPlan, make_plan
from simulation.writer import RunWriter, check_output_dir


def parse_frames(spec: str | None, n: int) -> range:
    """``A:B`` (Python slice semantics, either side optional) -> range of frame indices."""
    if spec is None:
        return range(n)
    parts = spec.split(":")
    if len(parts) != 2:
        raise ConfigError(f"--frames: expected A:B, got {spec!r}")
    try:
        a = int(parts[0]) if parts[0].strip() else 0
        b = int(parts[1]) if parts[1].strip() else n
    except ValueError:
        raise ConfigError(f"--frames: expected integers A:B, got {spec!r}") from None
    if a < 0 or b < 0:
        raise ConfigError(f"--frames: indices must be >= 0, got {spec!r}")
    if a >= b or a >= n:
        raise ConfigError(f"--frames: {spec!r} selects no frame of the {n} frames")
    return range(a, min(b, n))


def prepare(scenario, out: str | Path, frames: str | None = None,
            command: list[str] | None = None) -> tuple[RunPlan, RunWriter, range]:
    """All checks that can fail on user input, before Blender is touched."""
    frame_range = parse_frames(frames, scenario.n_frames)
    out = Path(out)
    check_output_dir(out)
    plan = make_plan(scenario)
    writer = RunWriter(out, plan, command)
    return plan, writer, frame_range


def _load_bpy():
    try:
        import bpy  # noqa: F401
    except ImportError as error:
        raise ConfigError(
            f"rendering needs Blender as a Python module (pip install 'granite-py[sim]'): {error}"
        ) from None


def render_run(plan: RunPlan, writer: RunWriter, frame_range: range,
               progress: Callable | None = None, seed_offset: int = 0) -> dict:
    """Render the unfinished frames of ``frame_range``; returns a small summary dict.

    ``progress(iterable, total)`` wraps the frame loop (e.g. tqdm). Finished frames are
    skipped; :meth:`RunWriter.finish` runs even when interrupted.
    """
    _load_bpy()
    from simulation.render import Renderer, software_versions
    from simulation.sensor import Sensor, blur_taps
    from simulation.terrain.scene import build_world

    s = plan.scenario
    todo = [i for i in frame_range if not writer.is_done(i)]
    writer.write_static(software_versions())
    summary = {"rendered": 0, "skipped": len(frame_range) - len(todo), "seconds": []}
    if not todo:
        writer.finish()
        return summary
    t0 = time.perf_counter()
    build_world(s, plan.model)
    summary["build_seconds"] = time.perf_counter() - t0
    renderer = Renderer(s)
    sensor = Sensor(s.sensor, s.camera, s.seed, s.render.grayscale, s.render.exposure)
    try:
        iterator = progress(todo, len(todo)) if progress else todo
        for i in iterator:
            motion = plan.motion_poses(i) if s.render.motion_blur else None
            t = time.perf_counter()
            rgb, depth = renderer.render(plan.poses[i], motion)
            blur = None
            if sensor.blurs:
                e = s.sensor.exposure_time
                ends = plan.exposure_poses(i, e, 2)
                blur = plan.exposure_poses(i, e, blur_taps(depth, s.camera, plan.poses[i], ends))
            image, info = sensor.capture(rgb, i, depth, plan.poses[i], blur)
            seconds = time.perf_counter() - t
            writer.write_frame(i, image, depth, seconds, info)
            summary["rendered"] += 1
            summary["seconds"].append(seconds)
    finally:
        renderer.close()
        writer.finish()
        sys.stdout.flush()
    return summary
