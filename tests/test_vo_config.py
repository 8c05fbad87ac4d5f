"""The documented configuration files, the reference preset and the metadata-driven validator."""

import argparse
import dataclasses
import tomllib
from pathlib import Path

import pytest

from granite.cli.main import main
from granite.cli.run_cmd import load_config
from granite.config_schema import check_value, field_types, has_limits
from granite.errors import ConfigError
from granite.estimator.config import VoConfig, field_limits

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
DEFAULT_FILE = CONFIGS / "mono_default.toml"
REFERENCE_FILE = CONFIGS / "reference.toml"


def _keys():
    """(table, field) of every key of every table."""
    for name, cls in VoConfig.sections().items():
        for f in dataclasses.fields(cls):
            yield name, f


def test_documented_file_lists_exactly_the_defaults():
    data = tomllib.loads(DEFAULT_FILE.read_text())
    assert VoConfig.load(DEFAULT_FILE) == VoConfig()
    written = tomllib.loads(VoConfig().to_toml())
    assert {k: set(v) for k, v in data.items()} == {k: set(v) for k, v in written.items()}


def test_reference_file_is_the_defaults_with_our_additions_off():
    data = tomllib.loads(REFERENCE_FILE.read_text())
    ref, default = VoConfig.load(REFERENCE_FILE), VoConfig()
    assert {k: set(v) for k, v in data.items()} == {k: set(v) for k, v in tomllib.loads(ref.to_toml()).items()}
    assert ref == VoConfig.reference()
    changed = {(name, key) for name in VoConfig.sections()
               for key, value in dataclasses.asdict(getattr(ref, name)).items()
               if value != getattr(getattr(default, name), key)}
    assert changed == {("optical_flow", "retry_min_flow"), ("optical_flow", "guess_min_zncc"),
                       ("optical_flow", "presmooth_sigma"), ("optical_flow", "pattern"),
                       ("optical_flow", "fb_noise_factor"), ("optical_flow", "guided_levels_above"),
                       ("optical_flow", "global_retry_min_lost"), ("optical_flow", "probe_points"),
                       ("optical_flow", "retry_out_of_view"),
                       ("estimator", "constant_velocity"), ("estimator", "motion_guided_tracking"),
                       ("estimator", "predict_before_estimate"), ("estimator", "tracked_rotation_guess"),
                       ("estimator", "prediction_depth_neighbours"),
                       ("estimator", "outlier_reoptimize_iterations"),
                       ("backend", "jacobian_reuse_steps"), ("backend", "no_motion_weight"),
                       ("estimator", "reinit_keeps_scale"), ("estimator", "init_max_candidates"),
                       ("estimator", "init_candidate_min_parallax"),
                       ("estimator", "init_keep_reference"), ("estimator", "entropy_iteration"),
                           ("estimator", "triangulate_needs_map"),
                       ("initialization", "parallax_distance"), ("initialization", "max_rotation_only_fraction"),
                       ("backend", "marg_seen_fraction")}
    # The features are really off: no median-flow retry, no guided pass, no constant velocity.
    assert ref.optical_flow.retry_min_flow == 0.0 and ref.optical_flow.guess_min_zncc == -1.0
    assert ref.optical_flow.presmooth_sigma == 0.0 and ref.optical_flow.local_retry_rounds == 0
    assert not (ref.estimator.constant_velocity or ref.estimator.motion_guided_tracking
                or ref.estimator.reinit_keeps_scale or ref.estimator.init_keep_reference
                or ref.estimator.refind_enabled)
    assert ref.estimator.init_max_candidates == 0 and ref.estimator.entropy_iteration == 4


def test_default_file_marks_exactly_our_keys():
    """The comment of every key says "ours:" exactly when its metadata says it is not the
    reference's setting, and the header names every key the reference preset changes."""
    lines = DEFAULT_FILE.read_text().splitlines()
    header = "\n".join(line for line in lines if line.startswith("#"))
    table = None
    for line in lines:
        if line.startswith("["):
            table = line.strip("[]")
        elif "=" in line and not line.startswith("#"):
            key, _, rest = line.partition("=")
            key = key.strip()
            f = next(f for f in dataclasses.fields(VoConfig.sections()[table]) if f.name == key)
            ours = field_limits(table, f).get("origin") == "ours"
            assert ("# ours:" in rest) == ours, f"[{table}] {key}"
            if "reference" in field_limits(table, f):
                assert key in header and key in REFERENCE_FILE.read_text().split("\n\n")[0]


def test_every_key_has_a_type_and_a_range():
    """A new key needs its range (field metadata or SECTION_LIMITS); booleans need none."""
    for name, f in _keys():
        typ = field_types(VoConfig.sections()[name])[f.name]
        assert typ in (bool, int, float, str), f"[{name}] {f.name}: unsupported type {typ}"
        if typ is not bool:
            assert has_limits(field_limits(name, f)), f"[{name}] {f.name} has no range"


def _probe_values(meta, typ):
    """Values on and just beyond each bound: (value, inside the range)."""
    out = []
    for bound, open_key, sign in (("lo", "lo_open", -1), ("hi", "hi_open", +1)):
        b = meta.get(bound)
        if b is None:
            continue
        step = 1 if typ is int else max(abs(b) * 1e-6, 1e-9)
        if meta.get(open_key):
            out += [(b, False), (b - sign * step, True)]
        else:
            out += [(b, True), (b + sign * step, False)]
    return out


def test_the_validator_accepts_only_what_the_dataclasses_accept():
    """At every bound, the validator and the table's own dataclass agree: a value inside the
    range builds the dataclass (whatever checks that class does itself), one outside is refused
    by the validator, naming the table and the key."""
    for name, f in _keys():
        cls = VoConfig.sections()[name]
        typ = field_types(cls)[f.name]
        if typ is bool:
            continue
        for value, inside in _probe_values(field_limits(name, f), typ):
            if inside:
                check_value(value, typ, field_limits(name, f), "x", ConfigError)
                try:
                    VoConfig.from_dict({name: {f.name: value}})  # builds cls(**{key: value})
                except ConfigError as error:  # only a constraint between keys may refuse it
                    assert any(t in str(error) for t in ("must not exceed", "[lm_lambda_min, lm_lambda_max]",
                                                            "must be >= fb_threshold_sq"))
            else:
                with pytest.raises(ConfigError, match=rf"^\[{name}\] {f.name}: must be"):
                    VoConfig.from_dict({name: {f.name: value}})


@pytest.mark.parametrize(
    "text, message",
    [
        ('[initialization]\nmin_parallax_deg = "5"\n',
         "[initialization] min_parallax_deg: must be a number, got '5'"),
        ("[estimator]\nentropy_iteration = 0\n", "[estimator] entropy_iteration: must be in [1, 1000], got 0"),
        ("[estimator]\nentropy_iteration = 8\n",
         "[estimator] entropy_iteration: must not exceed [backend] max_iterations (7), got 8"),
        ("[optical_flow]\nlevelz = 3\n", "[optical_flow] levelz: unknown key (known keys: border,"),
        ("[optical_flow]\nlevels = 2.0\n", "[optical_flow] levels: must be an integer, got 2.0"),
        ("[optical_flow]\nfast_min_threshold = 50\n",
         "[optical_flow] fast_min_threshold: must not exceed fast_threshold (40), got 50"),
        ("[backend]\nobs_std_dev = -1\n", "[backend] obs_std_dev: must be in (0, 10000], got -1.0"),
        ("[backend]\nuse_lm = 1\n", "[backend] use_lm: must be true or false, got 1"),
        ("[backend]\nhuber_threshold = nan\n", "[backend] huber_threshold: must be finite, got nan"),
        ("[estimator]\nkeyframe_entropy_fraction = 2.0\n",
         "[estimator] keyframe_entropy_fraction: must be in (0, 1], got 2.0"),
        ("[initialization]\nransac_confidence = 1.0\n",
         "[initialization] ransac_confidence: must be in (0, 1), got 1.0"),
        ("backend = 3\n", "[backend] must be a table"),
        ("levels = 3\n", "levels: a key outside any table"),
        ("[nonsense]\n", "[nonsense]: unknown table (known tables: optical_flow, backend, initialization, estimator)"),
        ("not toml = = 1", "not valid TOML"),
    ],
)
def test_bad_configuration_is_one_line_naming_file_table_and_key(tmp_path, text, message):
    path = tmp_path / "c.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        VoConfig.load(path)
    assert str(info.value).startswith(f"{path}: {message}")
    assert "\n" not in str(info.value)


def test_integers_are_accepted_for_numbers_and_kept_as_floats(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[initialization]\nmin_parallax_deg = 7\n[backend]\nmax_iterations = 9\n")
    config = VoConfig.load(path)
    assert config.initialization.min_parallax_deg == 7.0
    assert isinstance(config.initialization.min_parallax_deg, float)
    assert config.backend.max_iterations == 9


def test_programmatic_configurations_are_validated_too():
    with pytest.raises(ConfigError, match=r"\[estimator\] entropy_iteration: must be in"):
        dataclasses.replace(VoConfig(), estimator=dataclasses.replace(VoConfig().estimator, entropy_iteration=0))
    with pytest.raises(ConfigError, match=r"\[initialization\] min_parallax_deg: must be a number"):
        VoConfig(initialization=dataclasses.replace(VoConfig().initialization, min_parallax_deg="5"))


@pytest.mark.parametrize("command", ["run", "demo"])
def test_cli_bad_configuration_exits_2_with_one_line_before_any_work(tmp_path, capsys, command):
    config = tmp_path / "bad.toml"
    config.write_text('[initialization]\nmin_parallax_deg = "5"\n')
    out = tmp_path / "out"
    argv = [command, *([str(tmp_path / "no-such-dataset")] if command == "run" else []),
            "--out", str(out), "--config", str(config), "--quiet"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert f"{config}: [initialization] min_parallax_deg: must be a number, got '5'" in err
    assert not out.exists(), "nothing is written (nor rendered) before the configuration is checked"


@pytest.mark.parametrize("config_file", [None, REFERENCE_FILE])
def test_ablation_switches_apply_to_either_configuration(config_file):
    args = argparse.Namespace(config=config_file, finest_level_only=True, current_frame_keyframe=True)
    config = load_config(args)
    base = VoConfig.load(config_file) if config_file else VoConfig()
    assert config.optical_flow.detect_all_levels is False
    assert config.estimator.previous_frame_as_keyframe is False
    # Everything else is the chosen configuration's.
    assert dataclasses.replace(config.optical_flow, detect_all_levels=True) == base.optical_flow
    assert dataclasses.replace(config.estimator, previous_frame_as_keyframe=True) == base.estimator
    assert config.backend == base.backend and config.initialization == base.initialization


def test_range_text_of_open_and_half_open_bounds():
    from granite.config_schema import range_text

    assert range_text({"lo": 0, "hi": 1, "lo_open": True}) == "in (0, 1]"
    assert range_text({"lo": 0, "hi": 1}) == "in [0, 1]"
    assert range_text({"lo": 2}) == ">= 2" and range_text({"hi": 2, "hi_open": True}) == "< 2"
