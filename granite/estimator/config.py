"""The VO configuration: one TOML file with a table per component.

``[optical_flow]`` -> :class:`granite.optical_flow.OpticalFlowConfig`,
``[backend]`` -> :class:`granite.backend.config.BackendConfig`,
``[initialization]`` -> :class:`granite.estimator.initialization.InitializationConfig`,
``[estimator]`` -> :class:`EstimatorConfig`. Missing keys take the defaults: the reference
monocular configuration, except the keys whose metadata says ``origin="ours"``.
``configs/reference.toml`` is exactly the reference configuration (:meth:`VoConfig.reference`),
``configs/mono_default.toml`` documents every key with its default.

Validation (one validator for every table, :mod:`granite.config_schema`): a key's type is its
dataclass field's annotation, its allowed values come from the field's metadata
(:func:`granite.config_schema.spec_field`) or, for the dataclasses of other packages that carry
none, from :data:`SECTION_LIMITS`. Every problem is one :class:`ConfigError` line
``[table] key: message`` (``file: `` in front when read from a file); unknown tables and keys
are errors. A new key needs only its field and its range (field metadata, or an entry of
:data:`SECTION_LIMITS`).

Metadata beyond the ranges: ``origin="ours"`` marks a key that is not a setting of the
reference implementation (without it: the reference's setting, at the reference's value), and
``reference`` is the value that reproduces the reference's behaviour where our default differs.
"""

from __future__ import annotations

import dataclasses
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from granite.backend.config import BackendConfig
from granite.config_schema import (
    check_table,
    check_value,
    field_types,
    has_limits,
    limits,
    spec_field,
    toml_value,
    validate_instance,
)
from granite.errors import ConfigError
from granite.estimator.initialization import InitializationConfig
from granite.optical_flow import OpticalFlowConfig


@dataclass(frozen=True)
class EstimatorConfig:
    """Pipeline settings (paper Sec. IV-B..D; reference defaults except the three marked).

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
        triangulate_needs_map: ours (the reference: false). New landmarks get a finite
            inverse distance, and points at infinity are re-triangulated, only from a frame that
            observes at least ``min_finite_observations`` finite landmarks, i.e. whose
            translation the map measures. Without it, once every finite point has left the view
            (a long turn in place), the translation guessed by the motion model becomes the
            baseline, the points at infinity come back at an arbitrary scale and the map
            initialisation that should set it never runs (docs/estimator.md).
        min_triangulation_distance: a new landmark whose best baseline is shorter (map units)
            is inserted at infinity (d = 0).
        entropy_iteration: the keyframe decision is taken on the system linearised after this
            many Gauss-Newton steps. The reference takes 4; ours is 3 (measured: with 4 the
            640x480 spiral took 138 instead of 22 keyframes and its ATE rose from 0.057 to
            0.70 m; docs/estimator.md).
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
        init_max_candidates: not in the reference (0: its search, keyframes oldest first, the
            first that initialises wins): the map initialisation evaluates this many keyframes,
            those whose shared tracks show the most rotation-compensated parallax, and keeps
            the accepted hypothesis with the most inliers.
        init_candidate_min_parallax: candidates whose rotation-compensated track parallax
            (75th percentile) is below this fraction of ``[initialization] min_parallax_deg``
            are not tried (0: all are tried). Ours at 0.1: while the camera turns in place,
            initialisation is attempted every frame on pairs with almost no parallax (median
            0.06-0.11 deg on the rotation scenarios), and no accepted initialisation of the
            28 measured (bench, study, KITTI, assets) had less than 0.93 deg (0.18 of the
            5 deg threshold); docs/estimator.md.
        init_keep_reference: not in the reference: while no map exists, the keyframe with the
            most rotation-compensated parallax to the newest frame is never marginalised.
        keyframe_on_invalid_entropy: a missing or non-finite (singular) negative entropy forces
            a keyframe, as in the reference (false: it never triggers one).
        keyframe_depth_change: not in the reference (0: off): a keyframe is also taken when
            the median depth of the current frame's finite landmarks differs from the newest
            keyframe's by more than the factor ``1 + keyframe_depth_change`` (the scene scale
            changed: climb, descent), at least ``min_frames_after_keyframe`` frames after a
            keyframe (:func:`granite.estimator.keyframes.median_depth`).
        keyframe_min_scale_links: not in the reference (0: off): a keyframe (the previous
            frame) is also taken when fewer than this many finite landmarks of the current
            frame are observed in two keyframes or more (their host counts), at least
            ``min_frames_after_keyframe`` frames after a keyframe. A landmark seen in two
            keyframes only fixes their relative pose up to the baseline's length, so a new
            keyframe whose landmarks all come from such pairs carries no scale from the map
            once the frames between leave the window (docs/estimator.md).
        refind_enabled: not in the reference: a mapped frame observing fewer than
            ``refind_below_finite`` finite landmarks re-finds the window's others from their
            predicted positions, tracking their host keyframe's patch
            (:mod:`granite.estimator.recovery`).
        refind_fb_threshold_sq: forward-backward limit of a re-found point (squared pixels of
            its creation level).
        refind_min_zncc: minimum ZNCC of a re-found patch with its host patch.
        motion_guided_tracking: not in the reference: the frontend first tracks each point
            from where the constant-velocity pose predicts it (landmarks with d > 0 by their
            depth, tracks without a landmark by their neighbours' (``prediction_depth_neighbours``),
            the others by the infinite homography), then as the reference does.
        prediction_depth_neighbours: not in the reference (which has no prediction; 0: the
            infinite homography). With ``motion_guided_tracking``, a track without a landmark
            is predicted with the median depth of this many nearest tracks (pixel distance)
            whose landmarks have one (:func:`granite.estimator.motion_model.neighbour_depths`).
        predict_before_estimate: not in the reference (which has no prediction). With
            ``motion_guided_tracking``, frame k+1's predictions are made before frame k is
            estimated, so the concurrent pipeline tracks frame k+1 during the whole estimator
            step of frame k: from frame k's tracks, the window after frame k-1 and the motion
            model, whose pose for frame k is corrected by the rotation that maps frame k's
            predicted track bearings onto the tracked ones (Kabsch). False: from frame k's
            optimised pose (frame k+1's tracking waits for frame k's optimisation).
        tracked_rotation_guess: not in the reference (which starts from the last pose). With
            ``motion_guided_tracking`` and ``predict_before_estimate``, the optimisation of a
            frame starts from the constant-velocity position and the rotation its tracks
            measured: the rotation from the previous frame that the predictions assumed,
            corrected by the rotation that maps the predicted track bearings onto the tracked
            ones (Kabsch), on the previous frame's current estimate. In a fast turn the
            constant-velocity rotation is off by the angular acceleration (4-5 degrees per
            frame in the 20 s ``aggressive`` flight at 16 s), Gauss-Newton then did not
            converge in its 7 iterations and the estimate broke (docs/estimator.md). False:
            the constant-velocity pose.
        outlier_reoptimize_iterations: not in the reference (0: off; the reference publishes
            the estimate its outliers pulled on). When the outlier removal after a frame's
            optimisation takes at least ``outlier_reoptimize_min_fraction`` of the frame's own
            observations, the window is optimised again for this many iterations, so the
            published pose, the keyframe's new landmarks and the states marginalised next are
            estimated without them. A Huber-weighted outlier pulls like a residual at the Huber
            threshold, 2-10 times the pull of a tracked inlier, and with few observations per
            frame one outlier bent the estimate (docs/estimator.md).
        outlier_reoptimize_min_fraction: the share of the frame's observations the outlier
            removal must take for the re-optimisation (0: any outlier of the frame).
        outlier_reoptimize_states: what the re-optimisation after outlier removal optimises:
            ``"pose"`` the frame's pose alone, landmarks and other poses fixed (motion-only
            bundle adjustment on its own observations; the whole window when the frame hosts
            landmarks or is in the prior or the scale fix), ``"pose_and_landmarks"`` the pose
            and the landmarks it observes (the same fallback), ``"window"`` all states of the
            window. The outliers pull on the frame they were seen in; the next frame's
            optimisation re-estimates the rest without them (docs/estimator.md).
    """

    keyframe_entropy_fraction: float = spec_field(0.995, 0.0, 1.0, lo_open=True)
    keyframe_min_connected: int = spec_field(20, 0, 100000)
    min_frames_after_keyframe: int = spec_field(3, 0, 100000)
    previous_frame_as_keyframe: bool = spec_field(True)
    min_finite_observations: int = spec_field(5, 0, 100000)
    failure_min_connected: int = spec_field(7, 0, 100000)
    min_triangulation_distance: float = spec_field(0.03, 0.0, 1e6)
    triangulate_needs_map: bool = spec_field(True, origin="ours", reference=False)
    entropy_iteration: int = spec_field(3, 1, 1000, origin="ours", reference=4,
                                        doc="at most [backend] max_iterations")
    entropy_translation_finite_points: int = spec_field(5, 0, 100000)
    keyframe_extra_iterations: int = spec_field(2, 0, 1000)
    constant_velocity: bool = spec_field(True, origin="ours", reference=False)
    max_velocity_extrapolation: float = spec_field(5.0, 0.0, 1000.0, lo_open=True, origin="ours")
    motion_guided_tracking: bool = spec_field(True, origin="ours", reference=False)
    predict_before_estimate: bool = spec_field(True, origin="ours", reference=False)
    prediction_depth_neighbours: int = spec_field(8, 0, 1000, origin="ours", reference=0)
    tracked_rotation_guess: bool = spec_field(True, origin="ours", reference=False)
    outlier_reoptimize_iterations: int = spec_field(2, 0, 1000, origin="ours", reference=0)
    outlier_reoptimize_min_fraction: float = spec_field(0.005, 0.0, 1.0, origin="ours")
    outlier_reoptimize_states: str = spec_field(
        "pose", choices=("pose", "pose_and_landmarks", "window"), origin="ours")
    reinit_keeps_scale: bool = spec_field(True, origin="ours", reference=False)
    scene_distance_min_points: int = spec_field(20, 1, 100000, origin="ours")
    init_max_candidates: int = spec_field(3, 0, 1000, origin="ours", reference=0)
    init_candidate_min_parallax: float = spec_field(0.1, 0.0, 10.0, origin="ours", reference=0.0)
    init_keep_reference: bool = spec_field(True, origin="ours", reference=False)
    keyframe_on_invalid_entropy: bool = spec_field(True)
    keyframe_depth_change: float = spec_field(0.0, 0.0, 100.0, origin="ours", reference=0.0)
    keyframe_min_scale_links: int = spec_field(0, 0, 100000, origin="ours", reference=0)
    refind_enabled: bool = spec_field(False, origin="ours")
    refind_below_finite: int = spec_field(30, 0, 100000, origin="ours")
    refind_fb_threshold_sq: float = spec_field(0.3, 0.0, 1e4, lo_open=True, origin="ours")
    refind_min_zncc: float = spec_field(0.8, -1.0, 1.0, origin="ours")

    def __post_init__(self) -> None:
        validate_section(self, "estimator")


#: Ranges of the keys of the tables whose dataclasses (owned by other packages) carry no
#: validation metadata. A field's own metadata, when it has a range, takes precedence.
SECTION_LIMITS: dict[str, dict[str, dict[str, Any]]] = {
    "initialization": {
        "min_inliers": limits(5, 1000000),
        "min_parallax_deg": limits(0.0, 90.0, hi_open=True),
        "mean_distance": limits(0.0, 1e9, lo_open=True),
        "ransac_threshold_px": limits(0.0, 1e4, lo_open=True, origin="ours"),
        "ransac_confidence": limits(0.0, 1.0, lo_open=True, hi_open=True, origin="ours"),
        "min_bearing_z": limits(0.0, 1.0, hi_open=True, origin="ours"),
        "seed": limits(0, 2**31 - 1, origin="ours"),
        "refine_reach": limits(0.0, 1.0, origin="ours"),
        "refine_max_evaluations": limits(1, 1000000, origin="ours"),
        "parallax_distance": limits(choices=("mean", "median"), origin="ours", reference="mean"),
        "max_rotation_only_fraction": limits(0.0, 1.0, lo_open=True, origin="ours", reference=1.0),
    },
}


def field_limits(section: str, f: dataclasses.Field) -> dict[str, Any]:
    """Validation metadata of key ``f`` of table ``section``: the field's own when it has a
    range, choices or an origin, else its entry of :data:`SECTION_LIMITS` (else none)."""
    own = dict(f.metadata)
    if has_limits(own) or "origin" in own:
        return own
    return dict(SECTION_LIMITS.get(section, {}).get(f.name, own))


def _error(message: str) -> ConfigError:
    return ConfigError(message)


def _where(section: str, key: str) -> str:
    return f"[{section}] {key}:"


def validate_section(instance: Any, section: str) -> None:
    """Check every field of a table's dataclass instance (type and range, the field's own
    metadata or :data:`SECTION_LIMITS`); ints given for ``float`` keys become floats."""
    validate_instance(instance, section, lambda f: field_limits(section, f))


def _cross_checks(values: Mapping[str, Mapping[str, Any]]) -> None:
    """Constraints between keys (``values[table][key]``: every key's effective value), in the
    same one-line form."""
    of, be, est = values["optical_flow"], values["backend"], values["estimator"]
    checks = [
        (of["fast_min_threshold"] <= of["fast_threshold"], "optical_flow", "fast_min_threshold",
         f"must not exceed fast_threshold ({of['fast_threshold']})"),
        (of["fb_noise_factor"] <= 0.0 or of["fb_max_sq"] >= of["fb_threshold_sq"], "optical_flow",
         "fb_max_sq", f"must be >= fb_threshold_sq ({of['fb_threshold_sq']:g}) when fb_noise_factor > 0"),
        (be["lm_lambda_min"] <= be["lm_lambda_init"] <= be["lm_lambda_max"], "backend", "lm_lambda_init",
         f"must be in [lm_lambda_min, lm_lambda_max] = [{be['lm_lambda_min']:g}, {be['lm_lambda_max']:g}]"),
        (est["entropy_iteration"] <= be["max_iterations"], "estimator", "entropy_iteration",
         f"must not exceed [backend] max_iterations ({be['max_iterations']})"),
    ]
    for ok, section, key, message in checks:
        if not ok:
            raise ConfigError(f"{_where(section, key)} {message}, got {values[section][key]!r}")


def _construct(cls: type, kwargs: Mapping[str, Any], section: str):
    """``cls(**kwargs)``; a check of the class itself (one the ranges here should already
    cover) still becomes a ``[section]`` line."""
    try:
        return cls(**kwargs)
    except (ConfigError, TypeError, ValueError) as error:
        text = str(error)
        raise ConfigError(text if text.startswith(f"[{section}]") else f"[{section}] {text}") from None


@dataclass(frozen=True)
class VoConfig:
    """Everything a run needs; saved beside the run's outputs as ``config.toml``.

    Constructing one validates every table (:func:`validate_section`) and the constraints
    between keys, so ``dataclasses.replace`` cannot make an invalid configuration either.
    """

    optical_flow: OpticalFlowConfig = field(default_factory=OpticalFlowConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    initialization: InitializationConfig = field(default_factory=InitializationConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            validate_section(getattr(self, f.name), f.name)
        _cross_checks({f.name: dataclasses.asdict(getattr(self, f.name)) for f in dataclasses.fields(self)})

    @classmethod
    def sections(cls) -> dict[str, type]:
        """Table name -> the dataclass of the table."""
        return {f.name: type(f.default_factory()) for f in dataclasses.fields(cls)}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> VoConfig:
        """From decoded TOML; unknown tables or keys and bad values raise ConfigError."""
        sections = cls.sections()
        for name, value in data.items():
            if name not in sections:
                if isinstance(value, Mapping):
                    raise ConfigError(f"[{name}]: unknown table (known tables: {', '.join(sections)})")
                raise ConfigError(f"{name}: a key outside any table (keys belong in one of the "
                                  f"tables {', '.join(sections)})")
        given = {}
        for name, section_cls in sections.items():
            table = data.get(name, {})
            given[name] = check_table(
                section_cls, dict(table) if isinstance(table, Mapping) else table, _error,
                where=lambda key, name=name: _where(name, key),
                unknown=lambda key, known, name=name: f"{_where(name, key)} unknown key (known keys: {known})",
                name=name, meta=lambda f, name=name: field_limits(name, f),
            )
        _cross_checks({name: {**dataclasses.asdict(section_cls()), **given[name]}
                       for name, section_cls in sections.items()})
        return cls(**{name: _construct(section_cls, given[name], name) for name, section_cls in sections.items()})

    @classmethod
    def load(cls, path: str | Path) -> VoConfig:
        """Read and validate a TOML file; every error names the file."""
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ConfigError(f"{path}: configuration file not found") from None
        except IsADirectoryError:
            raise ConfigError(f"{path}: is a folder, not a configuration file") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
            raise ConfigError(f"{path}: not valid TOML ({error})") from None
        except OSError as error:
            raise ConfigError(f"{path}: cannot read the configuration ({error.strerror})") from None
        try:
            return cls.from_dict(data)
        except ConfigError as error:
            raise ConfigError(f"{path}: {error}") from None

    @classmethod
    def reference(cls) -> VoConfig:
        """The reference configuration: the defaults with every key that has a ``reference``
        value set to it (``configs/reference.toml``)."""
        changes = {}
        for name, section_cls in cls.sections().items():
            values = {}
            for f in dataclasses.fields(section_cls):
                meta = field_limits(name, f)
                if "reference" in meta:
                    values[f.name] = meta["reference"]
            changes[name] = section_cls(**values)
        return cls(**changes)

    def to_toml(self) -> str:
        """The complete configuration as TOML (every key, so a run can be repeated exactly)."""
        lines = ["# granite-py VO configuration (written by granite run)"]
        for f in dataclasses.fields(self):
            lines.append(f"\n[{f.name}]")
            for key, value in dataclasses.asdict(getattr(self, f.name)).items():
                lines.append(f"{key} = {toml_value(value)}")
        return "\n".join(lines) + "\n"
