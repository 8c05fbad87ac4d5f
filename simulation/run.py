"""One rendering run: validate everything (pure numpy), then build the world in Blender and
render the requested frames into a resumable output folder (:mod:`simulation.writer`)."""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
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


class _StopOnCtrlC:
    """Ctrl-C (SIGINT) ends the frame loop after the frame being rendered.

    Blender's own handler swallows a Ctrl-C (the run went on to its last frame), and a
    KeyboardInterrupt raised inside Cycles' Python render callback is printed and swallowed
    too; so the loop polls a flag instead (main thread only; elsewhere a no-op).
    """

    def __init__(self):
        self.requested = False
        self._previous = None
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)

    def _handle(self, signum, frame):
        if not self.requested:
            print("\ninterrupted: stopping after this frame (run the command again to resume)",
                  file=sys.stderr, flush=True)
        self.requested = True

    def restore(self) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
            self._previous = None


def render_run(plan: RunPlan, writer: RunWriter, frame_range: range,
               progress: Callable | None = None, seed_offset: int = 0) -> dict:
    """Render the unfinished frames of ``frame_range``; returns a small summary dict:
    ``rendered``, ``skipped``, ``seconds`` (per frame: its render plus its sensor model, as
    ``render_seconds`` in the manifest), ``wall_seconds`` (the frame loop, which overlaps
    a frame's sensor model and files with the next frame's render) and
    ``first_render_seconds`` (Cycles builds its BVH in the first render).

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

    def finish_frame(i: int, rgb: np.ndarray, depth: np.ndarray, render_seconds: float) -> None:
        """The camera model and the files of a rendered frame (worker thread)."""
        t = time.perf_counter()
        blur = None
        if sensor.blurs:
            e = s.sensor.exposure_time
            ends = plan.exposure_poses(i, e, 2)
            blur = plan.exposure_poses(i, e, blur_taps(depth, s.camera, plan.poses[i], ends))
        image, info = sensor.capture(rgb, i, depth, plan.poses[i], blur)
        seconds = render_seconds + time.perf_counter() - t
        writer.write_frame(i, image, depth, seconds, info)
        summary["rendered"] += 1
        summary["seconds"].append(seconds)

    # Cycles releases the GIL while it renders: the sensor model and the files of frame i
    # (one thread, ~0.1 s) run while frame i + 1 renders, at most one frame behind.
    t_loop = time.perf_counter()
    pending = None
    stop = _StopOnCtrlC()
    try:
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="granite-sim-frame") as pool:
            try:
                iterator = progress(todo, len(todo)) if progress else todo
                for i in iterator:
                    if stop.requested:
                        summary["interrupted"] = True
                        break
                    motion = plan.motion_poses(i) if s.render.motion_blur else None
                    t = time.perf_counter()
                    rgb, depth = renderer.render(plan.poses[i], motion)
                    seconds = time.perf_counter() - t
                    summary.setdefault("first_render_seconds", seconds)  # builds the BVH
                    if pending is not None:
                        previous, pending = pending, None
                        previous.result()  # a failure of the previous frame stops the run
                    pending = pool.submit(finish_frame, i, rgb, depth, seconds)
            finally:
                if pending is not None:  # also when interrupted: the rendered frame is kept
                    pending.result()
        summary["wall_seconds"] = time.perf_counter() - t_loop
    finally:
        stop.restore()
        renderer.close()
        writer.finish()
        sys.stdout.flush()
    return summary
