"""Study files of ``granite bench``: the bundled studies parse, every bad input is one error
line naming the file and the key, with exit status 2, before any work."""

from __future__ import annotations

from pathlib import Path

import pytest

from granite.bench.execute import plan_study
from granite.bench.study import load_study, parse_study, slugify
from granite.cli.main import main
from granite.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "studies" / "assets_smoke.toml"
PAPER = ROOT / "studies" / "paper_tables.toml"

GOOD_VARIANT = '\n[[variant]]\nname = "ours"\n'
GOOD_DATASET = f'\n[[scenario]]\ndataset = "{ROOT / "assets/sequences/aggressive"}"\n'


def test_smoke_study_parses():
    study = load_study(SMOKE)
    assert [s.id for s in study.sequences] == ["aggressive", "default"]
    assert [v.name for v in study.variants] == ["ours", "reference"]
    assert all(not s.rendered for s in study.sequences)
    assert len(study.runs()) == 4
    assert load_study("assets_smoke").name == "assets_smoke"  # bundled name


@pytest.mark.slow
def test_paper_tables_parses_and_lists_tasks(tmp_path):
    study = load_study(PAPER)  # every flight checked against its seed's terrain
    scenarios = {s.label for s in study.sequences}
    assert scenarios == {"spiral", "rotation", "hover", "survey", "framedrop", "aggressive"}
    assert len({s.seed for s in study.sequences}) >= 2
    assert {v.name for v in study.variants} == {"ours", "reference", "ours †", "ours ‡"}
    assert all(s.width == 320 and s.height == 240 for s in study.sequences)
    plan = plan_study(study, tmp_path)
    kinds = [t.kind for t in plan.tasks]
    assert kinds.count("vo") == kinds.count("evaluate") == len(study.runs())
    assert kinds.count("finalize") == len(study.sequences)
    assert kinds.count("render") == sum(len(s.chunks(study.frames_per_task)) for s in study.sequences)
    keys = set()
    for t in plan.tasks:  # dependencies come first
        assert set(t.deps) <= keys
        keys.add(t.key)


def test_scenario_entry_expands_seeds_and_overrides():
    study = parse_study({
        "seeds": [3, 4], "render": {"width": 64, "height": 48},
        "scenario": [{"scenario": "default", "frames": "0:10", "overrides": {"sensor": {"read_noise": 3.0}}},
                     {"scenario": "hover", "seeds": [7], "width": 80, "height": 60, "label": "h"}],
        "variant": [{"name": "ours †", "finest_level_only": True}],
    }, ROOT / "studies" / "x.toml", check_flights=False)
    ids = [s.id for s in study.sequences]
    assert ids == ["default_seed3_64x48_0-10", "default_seed4_64x48_0-10", "h_seed7_80x60_0-401"]
    text = study.sequences[0].scenario_text
    assert "seed = 3" in text and "read_noise = 3.0" in text and "threads = 1" in text
    assert study.sequences[0].fingerprint != study.sequences[1].fingerprint
    assert study.variants[0].slug == "ours_dagger" == slugify("ours †")
    assert study.variants[0].build().optical_flow.detect_all_levels is False


def test_variant_overrides_and_reference():
    study = parse_study({"scenario": [{"dataset": str(ROOT / "assets/sequences/default")}],
                         "variant": [{"name": "r", "config": "reference",
                                      "overrides": {"estimator": {"entropy_iteration": 2}}}]},
                        ROOT / "studies" / "x.toml")
    config = study.variants[0].build()
    assert config.estimator.entropy_iteration == 2
    assert config.estimator.reinit_keeps_scale is False  # the reference's value


BAD = [
    ("bogus = 1" + GOOD_DATASET + GOOD_VARIANT, "bogus: unknown key"),
    ("invalid = [", "invalid TOML"),
    (GOOD_DATASET, "needs at least one [[variant]]"),
    (GOOD_VARIANT, "needs at least one [[scenario]]"),
    ("delta = 0" + GOOD_DATASET + GOOD_VARIANT, "delta must be"),
    ('align = "umeyama"' + GOOD_DATASET + GOOD_VARIANT, "align must be one of"),
    ("seeds = 3" + GOOD_DATASET + GOOD_VARIANT, "seeds: must be a non-empty list"),
    ("seeds = [1, 1]" + GOOD_DATASET + GOOD_VARIANT, "seeds: a seed appears twice"),
    ('[render]\nwidth = "64"\n' + GOOD_DATASET + GOOD_VARIANT, "render.width must be an integer"),
    ('[render]\ncolour = true\n' + GOOD_DATASET + GOOD_VARIANT, "render.colour: unknown key"),
    ('[[scenario]]\nscenario = "nope"\n' + GOOD_VARIANT, "no such scenario file or bundled scenario"),
    ('[[scenario]]\nscenario = "default"\ndataset = "x"\n' + GOOD_VARIANT, "exactly one of scenario"),
    ('[[scenario]]\nscenario = "default"\nframes = "5:2"\n' + GOOD_VARIANT, "scenario[0].frames:"),
    ('[[scenario]]\nscenario = "default"\nwidth = 4\n' + GOOD_VARIANT, "scenario[0].width must be in"),
    ('[[scenario]]\nscenario = "default"\noverrides = { sensor = { read_noise = -1.0 } }\n' + GOOD_VARIANT,
     "sensor.read_noise must be"),
    ('[[scenario]]\nscenario = "default"\noverrides = { flight = { altitude_min = -50.0, altitude_max = -40.0 } }\n'
     + GOOD_VARIANT, "flight.altitude_min"),
    ('[[scenario]]\ndataset = "no/such/folder"\n' + GOOD_VARIANT, "scenario[0].dataset:"),
    ('[[scenario]]\ndataset = "../assets/sequences/default"\nseeds = [1]\n' + GOOD_VARIANT,
     "seeds: not for a dataset entry"),
    (GOOD_DATASET + '\n[[variant]]\nconfig = "reference"\n', "variant[0].name: missing"),
    (GOOD_DATASET + GOOD_VARIANT + GOOD_VARIANT, "is not unique"),
    (GOOD_DATASET + '\n[[variant]]\nname = "x"\nconfig = "nope.toml"\n', "variant[0].config: no configuration file"),
    (GOOD_DATASET + '\n[[variant]]\nname = "x"\nfinest_level_only = 1\n', "finest_level_only must be true or false"),
    (GOOD_DATASET + '\n[[variant]]\nname = "x"\noverrides = { estimator = { entropy_iteration = 0 } }\n',
     "[estimator] entropy_iteration: must be in [1, 1000], got 0"),
    (GOOD_DATASET + '\n[[variant]]\nname = "x"\noverrides = { nope = { a = 1 } }\n', "[nope]: unknown table"),
    (GOOD_DATASET + '\n[[variant]]\nname = "x"\nablation = true\n', "variant[0].ablation: unknown key"),
]


@pytest.mark.parametrize("text, message", BAD, ids=[m for _, m in BAD])
def test_bad_study_is_one_line_and_exit_2(tmp_path, capsys, text, message):
    (tmp_path / "studies").mkdir()
    study = tmp_path / "studies" / "bad.toml"
    study.write_text(text.replace('"../assets', f'"{ROOT}/assets'))
    with pytest.raises(ConfigError) as info:
        load_study(study, check_flights=False)
    assert message in str(info.value) and str(study) in str(info.value)
    assert main(["bench", str(study), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("granite bench: error: ") and message in err[0]
    assert not (tmp_path / "out" / "results.csv").exists()


def test_bad_command_lines(tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(["bench", str(SMOKE), "--out", str(tmp_path), "--workers", "2", "--scheduler", "tcp://127.0.0.1:1"])
    assert info.value.code == 2
    with pytest.raises(SystemExit) as info:
        main(["bench", str(SMOKE), "--out", str(tmp_path), "--workers", "0"])
    assert info.value.code == 2
    capsys.readouterr()
    assert main(["bench", "no_such_study", "--out", str(tmp_path)]) == 2
    assert "no such study file or bundled study" in capsys.readouterr().err
    assert main(["bench", str(SMOKE), "--out", str(tmp_path), "--tls-cert", "x.pem"]) == 2
    assert "TLS needs all of" in capsys.readouterr().err


@pytest.mark.parametrize("address, message", [
    ("notanaddr", "expected HOST:PORT or :PORT, got 'notanaddr'"),
    (":x", "the port must be an integer 0-65535, got 'x'"),
    ("127.0.0.1:65536", "the port must be an integer 0-65535, got '65536'"),
])
def test_bad_dashboard_address_is_one_line(tmp_path, capsys, address, message):
    with pytest.raises(SystemExit) as info:
        main(["bench", str(SMOKE), "--out", str(tmp_path / "out"), "--workers", "1", "--dashboard-address", address])
    err = capsys.readouterr().err
    assert info.value.code == 2 and err.count("\n") == 1
    assert err.startswith("granite bench: error: argument --dashboard-address: ") and message in err
    assert not (tmp_path / "out").exists()


def test_cluster_that_fails_to_start_is_one_line(tmp_path, capsys, monkeypatch):
    def fail(workers, dashboard_address):
        raise RuntimeError("Cluster failed to start: [Errno -2] Name or service not known")

    monkeypatch.setattr("granite.bench.execute.local_cluster", fail)
    argv = ["bench", str(SMOKE), "--out", str(tmp_path / "out"), "--workers", "1",
            "--dashboard-address", "nosuchhost.invalid:8787"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err == ("granite bench: error: the local Dask cluster failed to start (dashboard nosuchhost.invalid:8787): "
                   "Cluster failed to start: [Errno -2] Name or service not known\n")
    assert not (tmp_path / "out").exists()


def test_dry_run_lists_the_runs(tmp_path, capsys):
    assert main(["bench", str(SMOKE), "--out", str(tmp_path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "4 runs; 8 tasks to run" in out and "vo       default / reference" in out
    assert not (tmp_path / "results.csv").exists()


def test_a_finished_run_counts_only_for_the_configuration_that_made_it(tmp_path):
    """Resuming a study keeps a VO run only when its marker records the variant's current
    configuration: an edited variant (overrides, ablation) or an old marker is run again."""
    import dataclasses
    import json

    from granite.bench import tasks

    study = load_study(SMOKE)
    seq, variant = study.runs()[0]

    def vo_tasks():
        return sum(t.kind == "vo" for t in plan_study(study, tmp_path).tasks)

    assert vo_tasks() == 4
    marker = tasks.vo_marker(tmp_path, seq, variant)
    marker.parent.mkdir(parents=True)
    marker.write_text(json.dumps({"wall_s": 1.0, "config": tasks.config_fingerprint(variant)}))
    assert vo_tasks() == 3
    edited = dataclasses.replace(variant, overrides={"backend": {"max_keyframes": 9}})
    ablated = dataclasses.replace(variant, finest_level_only=True)
    assert len({tasks.config_fingerprint(v) for v in (variant, edited, ablated)}) == 3
    assert not tasks.vo_done(tmp_path, seq, edited) and not tasks.vo_done(tmp_path, seq, ablated)
    marker.write_text(json.dumps({"wall_s": 1.0}))  # a marker of before the fingerprint
    assert vo_tasks() == 4
    marker.write_text("not json")
    assert vo_tasks() == 4
