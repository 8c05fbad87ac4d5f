"""Recordings written by `granite run --rerun` and `granite view`, read back with rerun's API."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import rerun as rr

from granite.cli.main import main
from granite.errors import InputError
from granite.estimator.diagnostics import FrameDiagnostics, read_diagnostics, write_diagnostics
from granite.estimator.records import FrameRecord, write_records
from granite.io import open_dataset, write_tum
from granite.trajectory import Trajectory
from granite.visualization.colors import INFINITY_COLOR, UNMAPPED_COLOR, inverse_distance_colors
from granite.visualization.rerun_logger import frustum_wireframes
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


def dataset_of(run_dir):
    import json

    return json.loads((run_dir / "summary.json").read_text())["dataset"]


def _column(table, name):
    return table.column(name).to_pylist()


@pytest.mark.slow
@pytest.mark.parametrize("recording", ["live.rrd", "recording.rrd"])
def test_recording_holds_images_points_trajectories_and_series(run, recording):
    run_dir, N, n_gt = run
    rec = rr.dataframe.load_recording(str(run_dir / recording))
    table = rec.view(index="frame", contents="/**").select().read_all()
    frames = _column(table, "frame")
    assert sorted(frames) == list(range(N))
    diags = {d.frame_index: d for d in read_diagnostics(run_dir / "diagnostics.csv")}
    # Images are logged as the dataset's PNG bytes (no re-encoding): they decode to the frames.
    images = table.column("/world/camera/image:Blob")
    assert len(images) - images.null_count == N
    k = frames.index(N // 2)
    blob = images[k].values[0].values.to_numpy(zero_copy_only=False).astype(np.uint8)
    decoded = cv2.imdecode(blob, cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(decoded, open_dataset(dataset_of(run_dir)).frame(N // 2).image)
    tracked = _column(table, "/plots/tracked_points:Scalar")
    positions = _column(table, "/world/camera/image/tracks:Position2D")
    colors = _column(table, "/world/camera/image/tracks:Color")
    halves = _column(table, "/world/camera/image/patches:HalfSize2D")
    centres_2d = _column(table, "/world/camera/image/patches:Position2D")
    for f, n_plot, pos, col, half in zip(frames, tracked, positions, colors, halves):
        assert n_plot == [diags[f].tracked_points]
        assert len(pos) == diags[f].tracked_points
        assert len(col) == len(pos) == len(half)
    # Patch outlines: centred on the track, half size 5.25 px * 2^level at the creation level.
    k = frames.index(N - 1)
    np.testing.assert_allclose(centres_2d[k], positions[k])
    half = np.array(halves[k], dtype=np.float64)
    levels = np.log2(half[:, 0] / 5.25)
    np.testing.assert_array_equal(half[:, 0], half[:, 1])
    np.testing.assert_allclose(levels, np.round(levels), atol=1e-5)
    assert levels.min() > -1e-5 and levels.max() > 0.5  # some patches from coarser levels
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
    # The scale-drift indicator: one point per frame where diagnostics.csv defines it.
    for series, column in (("scale_drift_indicator", "scale_drift_indicator"),
                           ("scale_drift_indicator_ref", "scale_drift_indicator_ref")):
        logged = [v[0] for v in _column(table, f"/plots/{series}:Scalar") if v]
        expected = [getattr(d, column) for d in diags.values() if getattr(d, column) is not None]
        assert len(logged) == len(expected)
        np.testing.assert_allclose(sorted(logged), sorted(expected), rtol=1e-12)
    # 0 where Λ is defined, 1 where it found no scale information, nothing elsewhere
    logged = [v[0] for v in _column(table, "/plots/scale_unobservable:Scalar") if v]
    no_scale = [d for d in diags.values() if d.scale_drift_reason.startswith("no scale information")]
    defined = [d for d in diags.values() if d.scale_drift_indicator is not None]
    assert sorted(logged) == [0.0] * len(defined) + [1.0] * len(no_scale)
    # Keyframe frustums: every frame shows the window's keyframes (one strip per keyframe).
    strips = _column(table, "/world/keyframes:LineStrip3D")
    shown = [len(v) for f, v in zip(frames, strips) if v is not None]
    assert len(shown) == N and min(shown) >= 1 and max(shown) >= 2


def test_frustum_wireframe_reaches_the_image_corners_at_the_given_depth():
    K = np.array([[200.0, 0, 160], [0, 210.0, 120], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    strip = frustum_wireframes(T[None], K, (320, 240), 0.5)[0] - T[:3, 3]
    apex = np.all(strip == 0, axis=1)
    assert apex.sum() == 2
    corners = strip[~apex]
    np.testing.assert_allclose(corners[:, 2], 0.5)
    pixels = corners @ K.T / corners[:, 2:]
    assert {tuple(np.round(p[:2]).astype(int)) for p in pixels} == {(0, 0), (320, 0), (320, 240), (0, 240)}
    edges = {frozenset((tuple(a), tuple(b))) for a, b in zip(strip[:-1], strip[1:])}
    assert len(edges) == 8  # the four rectangle sides and the four edges to the apex

def test_view_of_missing_run_is_a_clear_error(tmp_path, capsys):
    assert main(["view", str(tmp_path / "nope")]) == 2
    assert "run folder not found" in capsys.readouterr().err


def _one_frame_run(root: Path, dataset: Path | str = SEQUENCES / "default") -> Path:
    """A run folder of ``dataset``'s first frame, written without running the VO."""
    run_dir = root / "run"
    run_dir.mkdir(parents=True)
    (run_dir / "summary.json").write_text(json.dumps({"dataset": str(dataset)}))
    write_tum(run_dir / "trajectory.tum", Trajectory(np.zeros(1), np.eye(4)[None]))
    write_diagnostics(run_dir / "diagnostics.csv", [FrameDiagnostics(0.0, 0, 0, "init")])
    write_records(run_dir / "landmarks.npz", [FrameRecord(0, 0.0)])
    return run_dir


def _one_error_line(capsys, *words: str) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("granite view: error: ") and "Traceback" not in err, err
    assert all(w in err for w in words), err
    return err


def test_view_of_a_one_frame_run_writes_only_the_recording(tmp_path):
    run_dir = _one_frame_run(tmp_path)
    before = {p.name for p in run_dir.iterdir()}
    assert main(["view", str(run_dir)]) == 0
    assert {p.name for p in run_dir.iterdir()} - before == {"recording.rrd"}  # no temporary file left


def test_view_of_landmarks_that_are_not_a_zip_is_one_line(tmp_path, capsys):
    run_dir = _one_frame_run(tmp_path)
    records = run_dir / "landmarks.npz"
    records.write_bytes(records.read_bytes()[:100])
    assert main(["view", str(run_dir)]) == 2
    _one_error_line(capsys, str(records), "not a granite run records file")
    assert not (run_dir / "recording.rrd").exists()


@pytest.mark.parametrize("summary, words", [
    ([1, 2], ("summary.json: top level must be a JSON object",)),
    ({"dataset": 5}, ("summary.json", '"dataset" must be a folder path', "got 5", "--dataset")),
    ({"frames": 1}, ("summary.json", '"dataset" must be a folder path', "got None")),
])
def test_view_of_a_bad_summary_is_one_line(tmp_path, capsys, summary, words):
    run_dir = _one_frame_run(tmp_path)
    (run_dir / "summary.json").write_text(json.dumps(summary))
    assert main(["view", str(run_dir)]) == 2
    _one_error_line(capsys, *words)
    assert not (run_dir / "recording.rrd").exists()


def test_view_says_the_missing_dataset_came_from_summary_json(tmp_path, capsys, monkeypatch):
    run_dir = _one_frame_run(tmp_path / "runs", dataset="gone/default")
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    assert main(["view", str(run_dir)]) == 2
    _one_error_line(capsys, f"{run_dir / 'summary.json'}: dataset folder 'gone/default'",
                    str(tmp_path / "elsewhere" / "gone" / "default"),  # the current folder first,
                    str(tmp_path / "runs" / "gone" / "default"), "--dataset")  # then beside the run


def test_view_finds_a_relative_dataset_beside_the_run_folder(tmp_path, monkeypatch):
    (tmp_path / "runs").mkdir()
    (tmp_path / "runs" / "ds").symlink_to(SEQUENCES / "default")
    run_dir = _one_frame_run(tmp_path / "runs", dataset="ds")
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    assert main(["view", str(run_dir)]) == 0


def test_view_that_fails_while_logging_leaves_no_recording(tmp_path, capsys, monkeypatch):
    from granite.visualization.run_view import RunView

    def fail(view, trajectory):
        raise InputError("simulated failure")

    run_dir = _one_frame_run(tmp_path)
    before = {p.name for p in run_dir.iterdir()}
    monkeypatch.setattr(RunView, "finish", fail)
    assert main(["view", str(run_dir)]) == 2
    _one_error_line(capsys, "simulated failure")
    assert {p.name for p in run_dir.iterdir()} == before  # neither recording.rrd nor a temporary file


def test_run_that_fails_leaves_no_recording(tmp_path, capsys, monkeypatch):
    def fail(*args, **kwargs):
        raise InputError("simulated failure")

    monkeypatch.setattr("granite.cli.run_cmd.run_vo", fail)
    rrd = tmp_path / "recordings" / "live.rrd"
    argv = ["run", str(SEQUENCES / "default"), "--out", str(tmp_path / "out"), "--rerun", str(rrd), "--quiet"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "simulated failure" in err
    assert not rrd.parent.exists() or not any(rrd.parent.iterdir())



def test_scale_unobservable_marks_frames_whose_window_has_no_scale():
    from granite.backend.scale_drift import NO_SCALE_ANCHOR, NO_SCALE_LINK
    from granite.visualization.run_view import scale_unobservable

    def diag(value=None, reason=""):
        return FrameDiagnostics(0.0, 0, 0, "tracking", scale_drift_indicator=value, scale_drift_reason=reason)
    assert scale_unobservable(diag(0.02)) == 0.0
    assert scale_unobservable(diag(reason=NO_SCALE_LINK)) == 1.0
    assert scale_unobservable(diag(reason=NO_SCALE_ANCHOR)) == 1.0
    assert scale_unobservable(diag(reason="fewer than 3 keyframes")) is None
    assert scale_unobservable(diag()) is None


def test_final_landmarks_are_each_frames_records_sent_in_chunks(tmp_path, monkeypatch):
    """The landmarks a run view sends when it finishes (spooled to temporary files while the
    run goes, sent a few frames per call) are, frame for frame, the records' world points
    (float32, no ground truth: identity alignment) in their inverse-distance colours, across
    chunk boundaries and with empty frames between."""
    from granite.visualization import run_view

    monkeypatch.setattr(run_view, "SEND_FRAMES", 3)
    rng = np.random.default_rng(4)
    n = 8
    counts = [5, 0, 7, 1, 0, 4, 9, 2]
    records = [FrameRecord(i, 0.05 * i, keyframe_ids=(max(0, i - 1), i),
                           landmarks_w=rng.normal(size=(c, 3)).astype(np.float32),
                           landmarks_inverse_distance=rng.uniform(0, 1, c).astype(np.float32))
               for i, c in enumerate(counts)]
    view = run_view.RunView("chunks", None, None, tmp_path / "v.rrd")
    for r in records:
        view.log_frame(r, None, FrameDiagnostics(r.timestamp, r.index, 0, "tracking"))
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n)
    view.finish(Trajectory(np.array([r.timestamp for r in records]), poses, np.zeros(n, np.int64)))
    table = rr.dataframe.load_recording(str(tmp_path / "v.rrd")).view(
        index="frame", contents="/world/landmarks/**").select().read_all()
    by_frame = dict(zip(_column(table, "frame"), zip(_column(table, "/world/landmarks:Position3D"),
                                                      _column(table, "/world/landmarks:Color"))))
    for r in records:
        points, colors = by_frame[r.index]
        np.testing.assert_array_equal(np.array(points, np.float32).reshape(-1, 3), r.landmarks_w)
        expected = inverse_distance_colors(r.landmarks_inverse_distance, 1.0)
        packed = [int.from_bytes(bytes([*c, 255]), "big") for c in expected]
        assert list(colors) == packed
