"""The run folder as other tools see it: plain TUM that evo reads, the sub-maps beside it,
KITTI poses, skipped frames left out, one RPE Δ for every command, warnings counted, and bad
output paths refused before any work. Ground truth comes from the generator (planar_scene)."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from granite.cli.main import build_parser, main
from granite.estimator.diagnostics import read_diagnostics
from granite.estimator.vo import MonocularVO
from granite.evaluation import DEFAULT_RPE_DELTA
from granite.io import read_tum, write_tum
from granite.trajectory import Trajectory
from planar_scene import default_flight, look_down_pose, write_planar_dataset

evo_file_interface = pytest.importorskip("evo.tools.file_interface")


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """60 frames of smooth flight; frames 20-22 blank (rejected by the frontend), 30 corrupt."""
    ts, poses = default_flight(60)
    images = {i: np.zeros((240, 320), np.uint8) for i in (20, 21, 22)}
    images[30] = b"\x89PNG\r\n\x1a\n garbage"
    return write_planar_dataset(tmp_path_factory.mktemp("flight"), ts, poses, images=images), ts, poses


@pytest.fixture(scope="module")
def run_dir(flight, tmp_path_factory):
    root, _, _ = flight
    out = tmp_path_factory.mktemp("run") / "run"
    assert main(["run", str(root), "--out", str(out), "--quiet", "--format", "kitti"]) == 0
    return out


SKIPPED = {20, 21, 22, 30}


def test_trajectory_is_plain_tum_that_evo_reads_as_written(run_dir, flight):
    from evo.core import metrics, sync

    rows = [r for r in (run_dir / "trajectory.tum").read_text().splitlines() if not r.startswith("#")]
    assert {len(r.split()) for r in rows} == {8}
    traj = evo_file_interface.read_tum_trajectory_file(str(run_dir / "trajectory.tum"))
    ours = read_tum(run_dir / "trajectory.tum")
    assert np.allclose(traj.positions_xyz, ours.positions)
    # evo's Sim(3)-aligned APE (its own association and Umeyama) equals our ATE.
    gt = evo_file_interface.read_tum_trajectory_file(str(flight[0] / "groundtruth.tum"))
    gt, est = sync.associate_trajectories(gt, traj)
    est.align(gt, correct_scale=True)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((gt, est))
    evaluation = json.loads((run_dir / "evaluation.json").read_text())
    assert ape.get_statistic(metrics.StatisticsType.rmse) == pytest.approx(evaluation["ate_rmse"], rel=1e-6)


def test_kitti_poses_are_the_same_poses(run_dir):
    kitti = evo_file_interface.read_kitti_poses_file(str(run_dir / "trajectory.kitti"))
    ours = read_tum(run_dir / "trajectory.tum")
    assert np.allclose(np.array(kitti.poses_se3), ours.poses, atol=1e-12)


def test_skipped_frames_are_left_out_and_never_evaluated(run_dir, flight):
    _, ts, _ = flight
    traj = read_tum(run_dir / "trajectory.tum")
    estimated = [i for i in range(len(ts)) if i not in SKIPPED]
    assert np.allclose(traj.timestamps, 1.0 + ts[estimated])  # planar_scene starts at 1 s
    diags = read_diagnostics(run_dir / "diagnostics.csv")
    assert [d.frame_index for d in diags if d.state == "skipped"] == sorted(SKIPPED)
    evaluation = json.loads((run_dir / "evaluation.json").read_text())
    assert evaluation["num_poses"] == len(estimated)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["skipped_frames"] == 4 and summary["estimated_frames"] == len(estimated)
    assert sum(summary["frontend_rejections"].values()) == 3
    assert sum(summary["skipped_by_reason"].values()) == 1


def test_submaps_csv_matches_the_trajectory_and_the_diagnostics(run_dir):
    rows = np.loadtxt(run_dir / "submaps.csv", delimiter=",", skiprows=1)
    traj = read_tum(run_dir / "trajectory.tum")
    diags = [d for d in read_diagnostics(run_dir / "diagnostics.csv") if d.state != "skipped"]
    assert np.allclose(rows[:, 0], traj.timestamps, atol=1e-9)
    assert rows[:, 1].astype(int).tolist() == [d.frame_index for d in diags]
    assert rows[:, 2].astype(int).tolist() == [d.submap for d in diags]


def test_one_rpe_delta_for_every_command(run_dir, flight, capsys):
    """Every command defaults to the same Δ, and `granite eval` on the run folder reproduces the
    run's evaluation.json (sub-maps from submaps.csv)."""
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command").choices
    for command in ("run", "demo", "eval"):
        delta = next(a for a in sub[command]._actions if a.dest == "delta")
        assert delta.default == DEFAULT_RPE_DELTA, command
    capsys.readouterr()
    assert main(["eval", "--est", str(run_dir), "--gt", str(flight[0] / "groundtruth.tum"), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["submaps_source"] == str(run_dir / "submaps.csv")
    evaluation = json.loads((run_dir / "evaluation.json").read_text())
    assert evaluation["delta"] == DEFAULT_RPE_DELTA
    for key, value in evaluation.items():  # equal up to the TUM text round trip of the poses
        assert result[key] == (pytest.approx(value, rel=1e-9) if isinstance(value, float) else value), key


# --------------------------------------------------------------------------- granite eval


def _two_submap_estimate(tmp_path: Path):
    """Ground truth: a curve; estimate: sub-map 0 at half scale, sub-map 1 at twice the scale
    with another origin (as after a restart)."""
    t = np.arange(0.0, 10.0 + 1e-9, 0.05)
    gt = np.array([look_down_pose([2.0 * s, np.sin(s), 10.0 + 0.2 * s], yaw=0.1 * s) for s in t])
    est = gt.copy()
    sub = (t >= 5.0).astype(np.int64)
    est[sub == 0, :3, 3] = 0.5 * gt[sub == 0, :3, 3]
    est[sub == 1, :3, 3] = 2.0 * gt[sub == 1, :3, 3] + [3.0, -1.0, 0.5]
    write_tum(tmp_path / "gt.tum", Trajectory(t, gt))
    run = tmp_path / "run"
    run.mkdir()
    write_tum(run / "trajectory.tum", Trajectory(t, est), submap_column=False)
    lines = ["timestamp,frame_index,submap"] + [f"{s:.9f},{i},{k}" for i, (s, k) in enumerate(zip(t, sub))]
    (run / "submaps.csv").write_text("\n".join(lines) + "\n")
    write_tum(tmp_path / "nine.tum", Trajectory(t, est, sub))  # the older 9-column form
    return tmp_path / "gt.tum", run


def _eval_json(capsys, *args) -> dict:
    capsys.readouterr()
    assert main(["eval", *map(str, args), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_eval_aligns_each_submap_found_beside_the_estimate(tmp_path, capsys):
    gt, run = _two_submap_estimate(tmp_path)
    for est in (run, run / "trajectory.tum", tmp_path / "nine.tum"):
        r = _eval_json(capsys, "--est", est, "--gt", gt)
        assert r["restarts"] == 1 and r["ate_rmse"] < 1e-9, est
        assert r["submap_scales"] == {"0": pytest.approx(2.0), "1": pytest.approx(0.5)}
    assert _eval_json(capsys, "--est", run, "--gt", gt)["submaps_source"] == str(run / "submaps.csv")
    assert _eval_json(capsys, "--est", tmp_path / "nine.tum", "--gt", gt)["submaps_source"] == "9th column"
    one = _eval_json(capsys, "--est", run, "--gt", gt, "--submaps", "none")
    assert one["restarts"] == 0 and one["ate_rmse"] > 0.5  # one alignment cannot fit both


def test_eval_refuses_submaps_that_do_not_match(tmp_path, capsys):
    gt, run = _two_submap_estimate(tmp_path)
    csv = run / "submaps.csv"
    csv.write_text("\n".join(csv.read_text().splitlines()[:-3]) + "\n")
    capsys.readouterr()
    assert main(["eval", "--est", str(run), "--gt", str(gt)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{csv}: does not match the trajectory" in err


# --------------------------------------------------------------------------- failures


def test_failed_evaluation_writes_no_null_and_says_why(flight, tmp_path, capsys):
    """Ground truth 1000 s later than the images: the run succeeds, the evaluation cannot."""
    root, ts, poses = flight
    late = tmp_path / "late"
    write_planar_dataset(late, ts[:25], poses[:25])
    write_tum(late / "groundtruth.tum", Trajectory(1000.0 + ts[:25], poses[:25]))
    out = tmp_path / "run"
    out.mkdir()
    (out / "evaluation.json").write_text('{"stale": true}\n')  # from an earlier run
    assert main(["run", str(late), "--out", str(out), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert not (out / "evaluation.json").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert "does not overlap" in summary["evaluation_error"]
    assert "evaluation failed" in captured.err and "evaluation failed" in captured.out
    assert "Evaluation failed, no `evaluation.json` was written" in (out / "report.md").read_text()


def test_numerical_warnings_are_counted_per_frame_and_shown_once(flight, tmp_path, capsys, monkeypatch):
    root, _, _ = flight
    original = MonocularVO.estimate  # the estimator's step, in the sequential and concurrent modes

    def noisy(self, frame_id, timestamp, image, *args):
        if 5 <= frame_id < 12:
            np.array([1.0]) / np.array([0.0])  # numpy: RuntimeWarning, divide by zero
        return original(self, frame_id, timestamp, image, *args)

    monkeypatch.setattr(MonocularVO, "estimate", noisy)
    out = tmp_path / "run"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing may leak out unrecorded
        assert main(["run", str(root), "--out", str(out), "--quiet", "--max-frames", "15"]) == 0
    err = capsys.readouterr().err
    assert sum("divide by zero" in line for line in err.splitlines()) == 1
    counts = {d.frame_index: d.warnings for d in read_diagnostics(out / "diagnostics.csv")}
    assert [i for i, n in counts.items() if n] == list(range(5, 12))
    summary = json.loads((out / "summary.json").read_text())
    kinds = [w for w in summary["warnings"] if w["kind"] == "RuntimeWarning"]
    assert len(kinds) == 1 and kinds[0]["count"] == 7 and kinds[0]["first_frame"] == 5
    assert "divide by zero" in kinds[0]["message"]


@pytest.mark.parametrize("command", ["run", "demo"])
def test_unwritable_output_is_one_line_before_any_work(tmp_path, capsys, command):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    for out in (blocker, blocker / "run"):
        argv = [command, *([str(tmp_path / "no-such-dataset")] if command == "run" else []),
                "--out", str(out), "--quiet"]
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and str(out) in err and "Traceback" not in err
        assert "no-such-dataset" not in err  # refused before the dataset is even opened


def test_rerun_target_that_is_a_folder_is_refused(flight, tmp_path, capsys):
    assert main(["run", str(flight[0]), "--out", str(tmp_path / "o"), "--rerun", str(tmp_path), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is a folder" in err
    assert not (tmp_path / "o").exists()


def test_bad_options_are_one_line(tmp_path, capsys):
    for argv in (["run", "x", "--out", "o", "--max-frames", "0"], ["run", "x", "--out", "o", "--delta", "-2"],
                 ["run", "x", "--out", "o", "--format", "csv"]):
        with pytest.raises(SystemExit) as info:
            main(argv)
        err = capsys.readouterr().err
        assert info.value.code == 2 and err.count("\n") == 1 and "granite run: error:" in err


@pytest.mark.parametrize("option", ["--width", "--height", "--samples"])
def test_demo_image_options_are_checked_before_rendering(tmp_path, capsys, option):
    with pytest.raises(SystemExit) as info:
        main(["demo", "--out", str(tmp_path / "demo"), option, "0", "--quiet"])
    out, err = capsys.readouterr()
    assert info.value.code == 2 and out == ""  # granite-sim was not started
    assert err == f"granite demo: error: argument {option}: must be at least 1: '0' (see granite demo --help)\n"
    assert not (tmp_path / "demo").exists()


def test_view_reads_a_run_folder_with_skipped_frames(run_dir, tmp_path, capsys):
    """`granite view` pairs the poses (estimated frames only) with every frame's records."""
    import rerun as rr

    rrd = tmp_path / "view.rrd"
    assert main(["view", str(run_dir), "--rerun", str(rrd)]) == 0
    recording = rr.dataframe.load_recording(str(rrd))
    table = recording.view(index="frame", contents="/world/camera").select().read_all()
    frames = table.column("frame").to_pylist()
    translations = table.column("/world/camera:Translation3D").to_pylist()
    posed = {f for f, t in zip(frames, translations) if t is not None}
    estimated = set(np.loadtxt(run_dir / "submaps.csv", delimiter=",", skiprows=1)[:, 1].astype(int).tolist())
    assert posed == estimated and SKIPPED.isdisjoint(posed)  # a camera pose exactly where one was estimated


def test_a_first_run_says_that_numba_compiles(flight, tmp_path, capsys, monkeypatch):
    import granite._numba_cache

    monkeypatch.setattr(granite._numba_cache, "has_cached_kernels", lambda cache_dir=None, kernels=(): False)
    assert main(["run", str(flight[0]), "--out", str(tmp_path / "run"), "--max-frames", "5"]) == 0
    err = capsys.readouterr().err
    notices = [line for line in err.splitlines() if "numba compiles the kernels" in line]
    assert len(notices) == 1 and notices[0].startswith("granite run: first run")
    monkeypatch.setattr(granite._numba_cache, "has_cached_kernels", lambda cache_dir=None, kernels=(): True)
    assert main(["run", str(flight[0]), "--out", str(tmp_path / "run2"), "--max-frames", "5"]) == 0
    assert "numba compiles" not in capsys.readouterr().err
