"""Recordings written by `granite run --rerun` and `granite view`, read back with rerun's API."""

from __future__ import annotations

import numpy as np
import pytest
import rerun as rr

from granite.cli.main import main
from granite.estimator.diagnostics import read_diagnostics
from granite.visualization.colors import INFINITY_COLOR, UNMAPPED_COLOR, inverse_distance_colors
from planar_scene import default_flight, write_planar_dataset

N = 40


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("rr")
    ts, poses = default_flight(N)
    dataset = write_planar_dataset(root / "ds", ts, poses)
    out = root / "run"
    assert main(["run", str(dataset), "--out", str(out), "--quiet", "--rerun", str(out / "live.rrd")]) == 0
    assert main(["view", str(out)]) == 0
    return out


def _column(table, name):
    return table.column(name).to_pylist()


@pytest.mark.parametrize("recording", ["live.rrd", "recording.rrd"])
def test_recording_holds_images_points_trajectories_and_series(run_dir, recording):
    rec = rr.dataframe.load_recording(str(run_dir / recording))
    table = rec.view(index="frame", contents="/**").select().read_all()
    frames = _column(table, "frame")
    assert sorted(frames) == list(range(N))
    diags = {d.frame_index: d for d in read_diagnostics(run_dir / "diagnostics.csv")}
    images = _column(table, "/world/camera/image:ImageBuffer")
    assert sum(v is not None for v in images) == N
    tracked = _column(table, "/plots/tracked_points:Scalar")
    positions = _column(table, "/world/camera/image/tracks:Position2D")
    colors = _column(table, "/world/camera/image/tracks:Color")
    for f, n_plot, pos, col in zip(frames, tracked, positions, colors):
        assert n_plot == [diags[f].tracked_points]
        assert len(pos) == diags[f].tracked_points
        assert len(col) == len(pos)
    # Colours: grey tracks without a landmark, magenta at infinity, the ramp otherwise.
    packed = lambda c: int.from_bytes(bytes([*c, 255]), "big")  # noqa: E731
    palette = {packed(UNMAPPED_COLOR), packed(INFINITY_COLOR)}
    all_colors = {c for col in colors if col for c in col}
    assert packed(INFINITY_COLOR) in all_colors  # rotation-only start: points at infinity
    assert any(c not in palette for c in all_colors)  # finite landmarks after initialisation
    assert packed(inverse_distance_colors(np.array([0.5]))[0]) not in palette
    static = rec.view(index="frame", contents="/world/groundtruth/**").select_static().read_all()
    assert len(static.column("/world/groundtruth:LineStrip3D").to_pylist()[0][0]) == N
    est = rec.view(index="frame", contents="/world/estimate/**").select_static().read_all()
    assert sum(len(s) for s in est.column("/world/estimate:LineStrip3D").to_pylist()[0]) == N
    landmarks = _column(table, "/world/landmarks:Position3D")
    assert sum(v is not None and len(v) > 0 for v in landmarks) > N // 2
    for series in ("finite_landmarks", "infinite_landmarks", "keyframe", "submap"):
        assert sum(v is not None for v in _column(table, f"/plots/{series}:Scalar")) == N


def test_view_of_missing_run_is_a_clear_error(tmp_path, capsys):
    assert main(["view", str(tmp_path / "nope")]) == 2
    assert "run folder not found" in capsys.readouterr().err
