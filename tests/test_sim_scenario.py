"""Scenario files and the CLI's input checks: every bundled scenario is valid and flyable;
bad input gives one clear line and exit status 2 before anything is rendered."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from granite.errors import ConfigError
from simulation import cli
from simulation.plan import make_plan
from simulation.scenario import SCENARIO_DIR, load_scenario, parse_scenario, with_overrides

REQUIRED = {"default", "spiral", "rotation", "framedrop", "hover", "survey", "aggressive"}
BUNDLED = sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))


def test_required_scenarios_exist():
    assert REQUIRED <= set(BUNDLED)


@pytest.mark.slow
@pytest.mark.parametrize("name", BUNDLED)
def test_bundled_scenario_is_valid_and_flyable(name):
    s = load_scenario(name)
    assert s.name == name and s.flight.type in {"spiral", "rotation", "hover", "survey",
                                                "aggressive"}
    plan = make_plan(s)  # raises if the flight leaves the terrain or goes below ground
    assert len(plan.times) == s.n_frames
    np.testing.assert_allclose(np.diff(plan.times), 1.0 / s.camera.rate_hz)
    clearance = plan.poses[:, 2, 3] - plan.model.surface_height(plan.poses[:, 0, 3],
                                                               plan.poses[:, 1, 3])
    assert clearance.min() >= s.flight.clearance
    if name == "framedrop":
        assert plan.dropped.any() and not plan.dropped[: s.frame_drops.keep_first].any()
    else:
        assert not plan.dropped.any()


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "bad.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("text, message", [
    ("[camera]\nwidht = 320\n", "unknown key camera.widht"),
    ("colour = 1\n", "unknown key colour"),
    ("[camera]\nwidth = 4\n", "camera.width must be in [16, 8192], got 4"),
    ("[render]\nsamples = 2.5\n", "render.samples must be an integer"),
    ("[lighting]\nsun_elevation = 120.0\n", "lighting.sun_elevation must be in"),
    ("[flight]\ntype = \"loop\"\n", "flight.type must be one of"),
    ("[flight]\ntype = \"hover\"\nradius = 3.0\n", "unknown key flight.radius"),
    ("[terrain]\ncolor = [0.1, 0.2]\n", "terrain.color must have 3 elements"),
    ("[camera]\nmodel = \"kb4\"\nwidth = 320\nheight = 240\n", "square image"),
    ("[flight]\naltitude_min = 30.0\naltitude_max = 10.0\n", "altitude_min must not exceed"),
    ("[render]\nsamples = 4\nadaptive_min_samples = 8\n", "adaptive_min_samples must not exceed"),
    ("seed = -1\n", "seed must be in"),
    ("[render\nsamples = 1\n", "invalid TOML"),
])
def test_bad_values_name_file_and_key(tmp_path, text, message):
    path = _write(tmp_path, text)
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("(", r"\(")) as info:
        load_scenario(path)
    assert str(path) in str(info.value)


def test_flight_below_ground_is_refused():
    s = parse_scenario({"flight": {"type": "hover", "altitude": 0.2, "clearance": 1.0}},
                       "low.toml")
    with pytest.raises(ConfigError, match="below the terrain clearance"):
        make_plan(s)


def test_flight_off_the_terrain_is_refused():
    s = parse_scenario({"terrain": {"extent": 64.0}, "flight": {"type": "hover",
                                                               "center": [40.0, 0.0]}}, "far.toml")
    with pytest.raises(ConfigError, match="leaves the detailed terrain"):
        make_plan(s)


def test_overrides_rescale_intrinsics():
    s = load_scenario("default")
    h = with_overrides(s, width=320, height=240)
    assert (h.camera.width, h.camera.height) == (320, 240)
    assert h.camera.fx == s.camera.fx / 2 and h.camera.cy == (s.camera.cy + 0.5) / 2 - 0.5
    with pytest.raises(ConfigError, match="--samples"):
        with_overrides(s, samples=0)
    with pytest.raises(ConfigError, match="--width"):  # 0 is a value, not "no override"
        with_overrides(s, width=0)


def _run_cli(capsys, *argv) -> tuple[int, str]:
    code = cli.main(list(argv))
    err = capsys.readouterr().err.strip()
    return code, err


@pytest.mark.parametrize("make_args, message", [
    (lambda d: ["render", "no_such_scenario", "--out", str(d / "o")], "no such scenario"),
    (lambda d: ["render", str(_write(d, "[camera]\nfoo = 1\n")), "--out", str(d / "o")],
     "unknown key camera.foo"),
    (lambda d: ["render", str(_write(d, "[flight]\ntype = \"hover\"\naltitude = 0.1\n")),
                "--out", str(d / "o")], "below the terrain"),
    (lambda d: ["render", "default", "--out", str(d / "o"), "--frames", "500:600"],
     "selects no frame"),
    (lambda d: ["render", "default", "--out", str(d / "o"), "--frames", "x"], "--frames"),
])
def test_cli_bad_input_one_line_exit_2(tmp_path, capsys, make_args, message):
    code, err = _run_cli(capsys, *make_args(tmp_path))
    assert code == 2
    assert len(err.splitlines()) == 1 and err.startswith("granite-sim render: error:")
    assert message in err
    assert not (tmp_path / "o" / "mav0").exists()  # nothing rendered


@pytest.mark.parametrize("argv, message", [
    (["render", "default", "--out", "OUT", "--width", "0"],
     "granite-sim render: error: argument --width: must be positive, got 0 (see granite-sim render --help)"),
    ([], "granite-sim: error: the following arguments are required: COMMAND (see granite-sim --help)"),
])
def test_cli_option_errors_are_one_line(tmp_path, capsys, argv, message):
    with pytest.raises(SystemExit) as info:
        cli.main([str(tmp_path / "o") if a == "OUT" else a for a in argv])
    err = capsys.readouterr().err
    assert info.value.code == 2 and err == message + "\n"
    assert not (tmp_path / "o").exists()


def test_cli_unwritable_output(tmp_path, capsys):
    blocker = tmp_path / "file.txt"
    blocker.write_text("not a folder")
    code, err = _run_cli(capsys, "render", "default", "--out", str(blocker / "run"))
    assert code == 2 and "output folder is not writable" in err and len(err.splitlines()) == 1


def test_cli_refuses_to_mix_runs(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "manifest.json").write_text(json.dumps({"fingerprint": "0123"}))
    code, err = _run_cli(capsys, "render", "default", "--out", str(out))
    assert code == 2 and "different scenario" in err


def test_cli_list(capsys):
    assert cli.main(["list"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert {line.split()[0] for line in lines} == set(BUNDLED)
    assert all("INVALID" not in line for line in lines)
