"""The VO configuration: one TOML file with a table per component.

``[optical_flow]`` -> :class:`granite.optical_flow.OpticalFlowConfig`,
``[backend]`` -> :class:`granite.backend.config.BackendConfig`,
``[initialization]`` -> :class:`granite.estimator.initialization.InitializationConfig`,
``[estimator]`` -> :class:`EstimatorConfig`. Missing keys take the reference monocular defaults;
unknown tables or keys are errors. ``configs/mono_default.toml`` documents every key.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from granite.backend.config import BackendConfig
from granite.errors import ConfigError
from granite.estimator.initialization import InitializationConfig
from granite.optical_flow import OpticalFlowConfig


@dataclass(frozen=True)
class EstimatorConfig:
    """Pipeline settings (paper Sec. IV-B..D; reference defaults).

    Attributes:
        keyframe_entropy_fraction: a keyframe is taken when the negative entropy of the newest
            pose drops to this fraction of its running average since the last keyframe.
        keyframe_min_connected: a keyframe is forced when fewer points are connected.
        min_frames_after_keyframe: entropy drops are ignored for this many frames.
        previous_frame_as_keyframe: the paper's choice (Sec. IV-D); false = ablation ‡.
        min_finite_observations: map initialisation is attempted while the current frame
            observes fewer landmarks with d > 0.
        failure_min_connected: with at least two keyframes, fewer connected landmarks is a
            tracking failure (restart, new sub-map).
        min_triangulation_distance: a new landmark whose best baseline is shorter (map units)
            is inserted at infinity (d = 0).
        entropy_iteration: Gauss-Newton iteration after which the keyframe decision is taken.
        entropy_translation_finite_points: the keyframe entropy includes the newest pose's
            translation when more than this many finite landmarks are connected (rotation
            only otherwise; the reference's value).
        keyframe_extra_iterations: extra iterations after a keyframe was inserted.
        constant_velocity: not in the reference (which starts from the last pose): start each
            frame's optimisation from a constant-velocity prediction.
        max_velocity_extrapolation: the constant-velocity guess scales the last motion by the
            elapsed time over the last time step, at most by this factor (frame drops).
        reinit_keeps_scale: not in the reference (which takes the fixed initial scale): a map
            re-initialisation after the map was lost (every point at infinity, e.g. after a
            long turn in place) scales the new map so the scene keeps the mean distance it had
            in the last frame that saw enough finite landmarks, and the sub-map continues;
            false = the fixed initial scale and a new sub-map.
        scene_distance_min_points: the scene distance a re-initialisation keeps is updated
            from frames that see at least this many finite landmarks.
        motion_guided_tracking: not in the reference: the frontend first tracks each point
            from where the constant-velocity pose predicts it (landmarks with d > 0 by their
            depth, the others by the infinite homography), then as the reference does.
    """

    keyframe_entropy_fraction: float = 0.995
    keyframe_min_connected: int = 20
    min_frames_after_keyframe: int = 3
    previous_frame_as_keyframe: bool = True
    min_finite_observations: int = 5
    failure_min_connected: int = 7
    min_triangulation_distance: float = 0.03
    entropy_iteration: int = 4
    entropy_translation_finite_points: int = 5
    keyframe_extra_iterations: int = 2
    constant_velocity: bool = True
    max_velocity_extrapolation: float = 5.0
    motion_guided_tracking: bool = True
    reinit_keeps_scale: bool = True
    scene_distance_min_points: int = 20

    def __post_init__(self) -> None:
        if not 0.0 < self.keyframe_entropy_fraction <= 1.0:
            raise ConfigError("estimator: keyframe_entropy_fraction must be in (0, 1]")
        for name in ("keyframe_min_connected", "min_frames_after_keyframe", "min_finite_observations",
                     "failure_min_connected", "entropy_iteration", "keyframe_extra_iterations",
                     "entropy_translation_finite_points", "scene_distance_min_points"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ConfigError(f"estimator: {name} must be an integer >= 0, got {value!r}")
        if not (math.isfinite(self.min_triangulation_distance) and self.min_triangulation_distance >= 0):
            raise ConfigError("estimator: min_triangulation_distance must be >= 0")
        value = self.max_velocity_extrapolation
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
            raise ConfigError("estimator: max_velocity_extrapolation must be a positive number")
        for name in ("previous_frame_as_keyframe", "constant_velocity", "motion_guided_tracking",
                     "reinit_keeps_scale"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"estimator: {name} must be true or false")


def _from_table(cls, table: Mapping[str, Any], section: str):
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - known)
    if unknown:
        raise ConfigError(f"[{section}]: unknown key(s) {', '.join(unknown)}")
    try:
        return cls(**dict(table))
    except TypeError as error:
        raise ConfigError(f"[{section}]: {error}") from None


@dataclass(frozen=True)
class VoConfig:
    """Everything a run needs; saved beside the run's outputs as ``config.toml``."""

    optical_flow: OpticalFlowConfig = field(default_factory=OpticalFlowConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    initialization: InitializationConfig = field(default_factory=InitializationConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> VoConfig:
        sections = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - set(sections))
        if unknown:
            raise ConfigError(f"unknown table(s) {', '.join(unknown)}; known: {', '.join(sections)}")
        kwargs = {}
        for name in sections:
            table = data.get(name, {})
            if not isinstance(table, Mapping):
                raise ConfigError(f"[{name}] must be a table")
            default = sections[name].default_factory()
            kwargs[name] = _from_table(type(default), table, name)
        return cls(**kwargs)

    @classmethod
    def load(cls, path: str | Path) -> VoConfig:
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except FileNotFoundError:
            raise ConfigError(f"{path}: configuration file not found") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
            raise ConfigError(f"{path}: not valid TOML ({error})") from None
        try:
            return cls.from_dict(data)
        except ConfigError as error:
            raise ConfigError(f"{path}: {error}") from None

    def to_toml(self) -> str:
        """The complete configuration as TOML (every key, so a run can be repeated exactly)."""
        lines = ["# granite-py VO configuration (written by granite run)"]
        for f in dataclasses.fields(self):
            lines.append(f"\n[{f.name}]")
            for key, value in dataclasses.asdict(getattr(self, f.name)).items():
                lines.append(f"{key} = {_toml_value(value)}")
        return "\n".join(lines) + "\n"


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    raise TypeError(f"cannot write {value!r} as TOML")
