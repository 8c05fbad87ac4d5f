"""Output folder of one test-bench run (EuRoC/ASL layout plus test-bench extras)::

    OUT/
      calib.json                              Basalt calibration (pinhole or kb4)
      groundtruth.tum                         T_w_c of every frame (dropped ones included)
      scenario.toml                           the scenario file, copied verbatim
      manifest.json                           versions, seed, options, per-frame render time
      mav0/cam0/data/<ns>.png                 images (none for dropped frames)
      mav0/cam0/data.csv                      images present: "#timestamp [ns],filename"
      mav0/cam0/sensor.yaml                   EuRoC camera description (T_BS = identity)
      mav0/depth0/data/<ns>.npy | .png        planar depth of every frame (see simulation.depth)
      mav0/depth0/data.csv                    depth maps present
      mav0/state_groundtruth_estimate0/data.csv   EuRoC ground truth (body = camera)

Every file is written atomically, so an interrupted run leaves only complete files; a frame
is finished when its depth map and (unless dropped) its image exist.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import fcntl
import hashlib
import json
import os
import tempfile
from pathlib import Path

import cv2
import numpy as np

from granite.errors import ConfigError, InputError
from granite.io import (
    Calibration,
    atomic_path,
    atomic_write_text,
    write_calibration,
    write_euroc_groundtruth,
    write_euroc_image_list,
    write_sensor_yaml,
    write_tum,
)
from granite.trajectory import Trajectory
from simulation.depth import DEPTH_EXTENSIONS, write_depth
from simulation.scenario import scenario_to_dict
from simulation.sensor import describe as describe_sensor

MANIFEST_VERSION = 2  # 2: sensor model (manifest "sensor", per-frame "sensor")


def calibration_of(cam) -> Calibration:
    """Basalt calibration of the scenario camera (kb4 = equidistant, k1..k4 = 0)."""
    params = {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy}
    if cam.model == "kb4":
        params.update(k1=0.0, k2=0.0, k3=0.0, k4=0.0)
    return Calibration(cam.model, params, cam.width, cam.height)


def fingerprint(scenario) -> str:
    """Hash of everything that changes the rendered content (not the output options)."""
    d = scenario_to_dict(scenario)
    d.pop("source", None)
    d.pop("description", None)
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def check_output_dir(out: Path) -> None:
    """Create ``out`` if needed and prove it writable (InputError otherwise)."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=out, prefix=".write-test-"):
            pass
    except OSError as error:
        raise InputError(f"output folder is not writable: {error.strerror or error}", out) from None
    if not out.is_dir():
        raise InputError("output path is not a folder", out)


@contextlib.contextmanager
def folder_lock(out: Path):
    """An exclusive lock (flock) of the output folder itself around the writes that read what
    other processes wrote: several processes may render disjoint frame ranges into one folder
    (``granite bench``), and the image lists and the manifest each one writes must hold the
    frames of all of them. No lock file is left behind; where the filesystem cannot lock a
    folder (some network filesystems) this does nothing (``granite bench`` rewrites the lists
    after the last range anyway)."""
    fd = os.open(out, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError:
            pass
        yield
    finally:
        os.close(fd)  # releases the lock


class RunWriter:
    """Writes one run (see module doc). Construct, then :meth:`write_static`, then
    :meth:`write_frame` per rendered frame and :meth:`finish` (also after interruption)."""

    def __init__(self, out: str | Path, plan, command: list[str] | None = None):
        self.out = Path(out)
        self.plan = plan
        s = plan.scenario
        self.scenario = s
        self.image_dir = self.out / "mav0" / "cam0" / "data"
        self.depth_dir = self.out / "mav0" / "depth0" / "data"
        self.depth_ext = DEPTH_EXTENSIONS[s.render.depth_format]
        self.fingerprint = fingerprint(s)
        self.command = command or []
        self.render_seconds: dict[int, float] = {}
        self.sensor_info: dict[int, dict] = {}
        self.software: dict[str, str] = {}
        self._check_existing()

    # ------------------------------------------------------------------ paths and state
    def image_path(self, i: int) -> Path:
        return self.image_dir / f"{int(self.plan.timestamps_ns[i])}.png"

    def depth_path(self, i: int) -> Path:
        return self.depth_dir / f"{int(self.plan.timestamps_ns[i])}{self.depth_ext}"

    def is_done(self, i: int) -> bool:
        """Frame ``i`` is finished (resumable runs skip it)."""
        return self.depth_path(i).is_file() and (
            bool(self.plan.dropped[i]) or self.image_path(i).is_file())

    def _check_existing(self) -> None:
        manifest = self.out / "manifest.json"
        if not manifest.is_file():
            return
        try:
            old = json.loads(manifest.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as error:
            raise InputError(f"cannot read the existing manifest: {error}", manifest) from None
        if old.get("fingerprint") != self.fingerprint:
            raise ConfigError(
                f"{self.out}: holds a run of a different scenario or options "
                f"(fingerprint {old.get('fingerprint')} != {self.fingerprint}); "
                "use another --out folder")
        self._merge_frames(old)

    def _merge_frames(self, manifest: dict) -> None:
        """Render times and sensor figures of the frames of ``manifest`` this writer has not
        rendered itself (earlier runs, or other processes rendering other frames of the folder)."""
        for frame in manifest.get("frames", []):
            i, sec = frame.get("index"), frame.get("render_seconds")
            if (isinstance(i, int) and sec is not None and 0 <= i < len(self.plan.times)
                    and i not in self.render_seconds):
                self.render_seconds[i] = float(sec)
                if isinstance(frame.get("sensor"), dict):
                    self.sensor_info[i] = frame["sensor"]

    # ------------------------------------------------------------------ writing
    def write_static(self, software: dict[str, str]) -> None:
        """Calibration, sensor.yaml, ground truth (all frames), scenario copy, manifest."""
        s, plan = self.scenario, self.plan
        self.software = dict(software)
        for d in (self.image_dir, self.depth_dir, self.out / "mav0" / "state_groundtruth_estimate0"):
            d.mkdir(parents=True, exist_ok=True)
        cam = s.camera
        write_calibration(self.out / "calib.json", calibration_of(cam))
        write_sensor_yaml(
            self.out / "mav0" / "cam0" / "sensor.yaml", np.eye(4), (cam.width, cam.height),
            [cam.fx, cam.fy, cam.cx, cam.cy],
            camera_model="pinhole",
            distortion_model="equidistant" if cam.model == "kb4" else "radial-tangential",
            distortion_coefficients=[0.0, 0.0, 0.0, 0.0], rate_hz=cam.rate_hz)
        gt = Trajectory(plan.timestamps_ns / 1e9, plan.poses)
        write_tum(self.out / "groundtruth.tum", gt)
        write_euroc_groundtruth(
            self.out / "mav0" / "state_groundtruth_estimate0" / "data.csv", gt)
        if s.source is not None:
            atomic_write_text(self.out / "scenario.toml", Path(s.source).read_text(encoding="utf-8"))
        with folder_lock(self.out):
            self.write_manifest()

    def write_frame(self, i: int, image: np.ndarray, depth: np.ndarray, seconds: float,
                    sensor_info: dict | None = None) -> None:
        """Depth first, image last (the image completes the frame); atomic files.
        ``sensor_info`` (exposure scale, blur taps) goes into the manifest."""
        write_depth(self.depth_path(i), depth, self.scenario.render.depth_format)
        if not self.plan.dropped[i]:
            arr = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
            with atomic_path(self.image_path(i)) as tmp:
                # level 1: the sensor noise leaves little to compress (level 9 takes 3.5x
                # the time for 3.5 % smaller files; docs/simulation.md)
                if not cv2.imwrite(str(tmp), arr, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
                    raise OSError(f"cannot write {self.image_path(i)}")
        self.render_seconds[i] = float(seconds)
        if sensor_info:
            self.sensor_info[i] = {k: float(v) for k, v in sensor_info.items()}

    def finish(self) -> None:
        """Lists of present images / depth maps and the manifest (safe to call repeatedly;
        under the folder lock, so the last of several processes lists every frame)."""
        with folder_lock(self.out):
            n = len(self.plan.times)
            ns = self.plan.timestamps_ns
            imgs = [i for i in range(n) if not self.plan.dropped[i] and self.image_path(i).is_file()]
            write_euroc_image_list(self.out / "mav0" / "cam0" / "data.csv", ns[imgs],
                                   [self.image_path(i).name for i in imgs])
            deps = [i for i in range(n) if self.depth_path(i).is_file()]
            write_euroc_image_list(self.out / "mav0" / "depth0" / "data.csv", ns[deps],
                                   [self.depth_path(i).name for i in deps])
            self.write_manifest()

    def write_manifest(self) -> None:
        """The manifest, merged with the one on disk: several processes may render disjoint
        frame ranges into one folder (``granite bench``), each keeping the others' frames
        (callers hold :func:`folder_lock`)."""
        s, plan = self.scenario, self.plan
        try:
            current = json.loads((self.out / "manifest.json").read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError):
            current = {}
        if current.get("fingerprint") == self.fingerprint:
            self._merge_frames(current)
        frames = [{
            "index": i,
            "timestamp_ns": int(plan.timestamps_ns[i]),
            "dropped": bool(plan.dropped[i]),
            "render_seconds": self.render_seconds.get(i),
            **({"sensor": self.sensor_info[i]} if i in self.sensor_info else {}),
        } for i in range(len(plan.times))]
        done = [v for v in self.render_seconds.values()]
        manifest = {
            "manifest_version": MANIFEST_VERSION,
            "scenario": s.name,
            "description": s.description,
            "source": None if s.source is None else str(s.source),
            "seed": s.seed,
            "fingerprint": self.fingerprint,
            "command": self.command,
            "software": self.software,
            "updated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "frame_count": len(frames),
            "dropped_count": int(np.sum(plan.dropped)),
            "rate_hz": s.camera.rate_hz,
            "depth": {"format": s.render.depth_format, "folder": "mav0/depth0/data",
                      "kind": "planar camera z in metres"},
            "mean_render_seconds": float(np.mean(done)) if done else None,
            "sensor": describe_sensor(s.sensor),
            "config": scenario_to_dict(s),
            "frames": frames,
        }
        atomic_write_text(self.out / "manifest.json", json.dumps(manifest, indent=1) + "\n")
