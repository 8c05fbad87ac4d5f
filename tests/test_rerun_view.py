"""Recordings written by `granite run --rerun` and `granite view`, read back with rerun's API."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rerun as rr

from granite.cli.main import main
from granite.estimator.diagnostics import read_diagnostics
from granite.io import open_dataset
from granite.visualization.colors import INFINITY_COLOR, UNMAPPED_COLOR, inverse_distance_colors
from planar_scene import default_flight, write_planar_dataset

N_PLANAR = 40
SEQUENCES = Path(__file__).resolve().parents[1] / "assets" / "sequences"


@pytest.fixture(scope="module", params=["planar", "default"])
def run(request, tmp_path_factory):
    """(run folder, number of frames): a synthetic planar scene and the pre-rendered Mars
    sequence ``default``, each run with ``--rerun`` and then viewed with ``granite view``."""
    root = tmp_path_factory.mktemp("rr")
    if request.param == "planar":
        ts, poses = default_flight(N_PLANAR)
        dataset, n = write_planar_dataset(root / "ds", ts, poses), N_PLANAR
    else:
        dataset = SEQUENCES / "default"
        n = len((dataset / "mav0" / "cam0" / "data.csv").read_text().splitlines()) - 1
    out = root / "run"
    assert main(["run", str(dataset), "--out", str(out), "--quiet", "--rerun", str(out / "live.rrd")]) == 0
    assert main(["view", str(out)]) == 0
    return out, n, len(open_dataset(dataset).ground_truth)


def _column(table, name):
    return table.column(name).to_pylist()


@pytest.mark.parametrize("recording", ["live.rrd", "recording.rrd"])
def test_recording_holds_images_points_trajectories_and_series(run, recording):
    run_dir, N, n_gt = run
    rec = rr.dataframe.load_recording(str(run_dir / recording))
    table = rec.view(index="frame", contents="/**").select().read_all()
    frames = _column(table, "frame")
    assert sorted(frames) == list(range(N))
    diags = {d.frame_index: d for d in read_diagnostics(run_dir / "diagnostics.csv")}
    images = table.column("/world/camera/image:ImageBuffer")
    assert len(images) - images.null_count == N
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
    assert len(static.column("/world/groundtruth:LineStrip3D").to_pylist()[0][0]) == n_gt
    est = rec.view(index="frame", contents="/world/estimate/**").select_static().read_all()
    assert sum(len(s) for s in est.column("/world/estimate:LineStrip3D").to_pylist()[0]) == N
    landmarks = _column(table, "/world/landmarks:Position3D")
    assert sum(v is not None and len(v) > 0 for v in landmarks) > N // 2
    for series in ("finite_landmarks", "infinite_landmarks", "keyframe", "submap"):
        assert sum(v is not None for v in _column(table, f"/plots/{series}:Scalar")) == N
    # Ground truth exists: the running scale error is plotted once the first second has passed.
    scale_error = [v[0] for v in _column(table, "/plots/relative_scale_error:Scalar") if v]
    times = sorted(d.timestamp for d in diags.values())
    after_first_second = sum(t >= times[0] + 1.0 - 1e-6 for t in times)
    assert 0.8 * after_first_second <= len(scale_error) <= after_first_second
    assert np.all(np.abs(scale_error) < 0.5)
    # Keyframe frustums: every frame shows the window's keyframes as posed pinholes.
    kf_columns = [c for c in table.column_names if c.startswith("/world/keyframes/")
                  and c.endswith(":PinholeProjection")]
    assert kf_columns
    shown = [sum(table.column(c)[i].as_py() is not None for c in kf_columns) for i in range(len(frames))]
    assert max(shown) >= 2 and min(shown) >= 1


def test_view_of_missing_run_is_a_clear_error(tmp_path, capsys):
    assert main(["view", str(tmp_path / "nope")]) == 2
    assert "run folder not found" in capsys.readouterr().err
