"""benchmarks/bench_render_paired.py: two source trees render the same frames side by side."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from _benchmarks import load_benchmark

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("extra, message", [
    (["--rounds", "0"], "--rounds and --repeats must be at least 1"),
    (["--frames", "1,x"], "comma-separated integers"),
    (["--frames", "99999"], "has frames 0.."),
    (["--size", "640"], "expected WxH"),
    (["--scenario", "no_such_scenario"], "no_such_scenario"),
    (["--tree-b", "/"], "holds no simulation/render.py"),
])
def test_bad_arguments_are_one_line_errors_with_status_2(extra, message, capsys):
    assert load_benchmark("bench_render_paired").main(["--tree-a", str(ROOT), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and message in err and "\n" not in err


@pytest.mark.slow
@pytest.mark.blender
def test_one_tree_against_itself_renders_identical_images(tmp_path, capsys):
    """Both sides run this checkout on a tiny scenario: the renders are identical and every
    paired frame gets a ratio (printed as the median over the rounds)."""
    pytest.importorskip("bpy")
    toml = tmp_path / "tiny.toml"
    toml.write_text(
        'name = "tiny"\nseed = 5\n[camera]\nwidth = 64\nheight = 48\nfx = 48.0\nfy = 48.0\n'
        'cx = 31.5\ncy = 23.5\n[terrain]\nextent = 16.0\nresolution = 0.5\nfar_extent = 40.0\n'
        '[flight]\ntype = "hover"\naltitude = 3.0\nduration = 0.2\npitch = 80.0\n')
    bench = load_benchmark("bench_render_paired")
    assert bench.main(["--tree-a", str(ROOT), "--scenario", str(toml), "--size", "64x48",
                       "--frames", "0,2", "--repeats", "1", "--rounds", "2"]) == 0
    out = capsys.readouterr().out
    assert out.count("round ") == 2 and "B / A over 4 paired frames" in out
    assert "images: identical" in out
    # a tree whose material brightens the sky term renders other images, and says so
    other = tmp_path / "tree"
    shutil.copytree(ROOT / "simulation", other / "simulation")
    (other / "granite").symlink_to(ROOT / "granite")
    (other / "scenarios").symlink_to(ROOT / "scenarios")
    material = other / "simulation" / "terrain" / "material.py"
    text = material.read_text()
    assert 'one_plus.inputs[1].default_value = 1.0' in text
    material.write_text(text.replace('one_plus.inputs[1].default_value = 1.0',
                                     'one_plus.inputs[1].default_value = 2.0'))
    assert bench.main(["--tree-a", str(ROOT), "--tree-b", str(other), "--scenario", str(toml),
                       "--size", "64x48", "--frames", "0", "--repeats", "1",
                       "--rounds", "1"]) == 0
    assert "images: differ" in capsys.readouterr().out


@pytest.mark.slow
@pytest.mark.blender
def test_a_side_that_fails_stops_the_round_with_its_error(tmp_path, capsys):
    """A tree that cannot render fails its side; the other side, waiting for it at the start
    barrier, is stopped, and the error names the side and its last message."""
    pytest.importorskip("bpy")
    broken = tmp_path / "tree"
    shutil.copytree(ROOT / "simulation", broken / "simulation")
    (broken / "granite").symlink_to(ROOT / "granite")
    (broken / "scenarios").symlink_to(ROOT / "scenarios")
    render = broken / "simulation" / "render.py"
    render.write_text(render.read_text() + '\nraise RuntimeError("broken tree (test)")\n')
    bench = load_benchmark("bench_render_paired")
    assert bench.main(["--tree-a", str(ROOT), "--tree-b", str(broken), "--size", "64x48",
                       "--frames", "0", "--repeats", "1", "--rounds", "1"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: side B") and "broken tree (test)" in err
