"""Plots and report.md of `granite run` and `granite demo`; the demo's order of checks and its
Ctrl-C behaviour. The demo's rendering step is replaced by a copy of a pre-rendered sequence
(no Blender needed); everything after it is the real command."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from granite.cli import demo_cmd
from granite.cli.main import main
from granite.estimator.diagnostics import FrameDiagnostics
from granite.estimator.vo import MonocularVO
from granite.io import read_tum
from granite.trajectory import Trajectory
from granite.visualization.report import write_plots

SEQUENCES = Path(__file__).resolve().parents[1] / "assets" / "sequences"


def _linked_images(report: Path) -> list[Path]:
    return [report.parent / m for m in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report.read_text())]


def _check_png(path: Path, width: int) -> np.ndarray:
    image = cv2.imread(str(path))
    assert image is not None, path
    assert image.shape[1] == width and image.std() > 10, path  # drawn, not blank
    return image


def _fake_render(copied: list):
    def render(args, dataset_dir: Path) -> int:
        copied.append(dataset_dir)
        if not dataset_dir.exists():
            shutil.copytree(SEQUENCES / "default", dataset_dir)
        return 0
    return render


@pytest.fixture(scope="module")
def demo_out(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "demo"
    mp = pytest.MonkeyPatch()
    mp.setattr(demo_cmd, "render", _fake_render([]))
    try:
        assert main(["demo", "--out", str(out), "--quiet"]) == 0
    finally:
        mp.undo()
    return out


@pytest.mark.slow
def test_demo_writes_plots_linked_from_both_reports(demo_out):
    for report, prefix in ((demo_out / "report.md", "run/"), (demo_out / "run" / "report.md", "")):
        images = _linked_images(report)
        names = sorted(p.name for p in images)
        assert names == ["points.png", "scale.png", "trajectory.png", "translation_error.png"], report
        assert images[0].name == "trajectory.png"
        assert all(str(p.relative_to(report.parent)).startswith(prefix) for p in images)
        for image in images:
            _check_png(image, {"trajectory.png": 1320}.get(image.name, 1210))
    evaluation = json.loads((demo_out / "evaluation.json").read_text())
    assert evaluation == json.loads((demo_out / "run" / "evaluation.json").read_text())
    text = (demo_out / "report.md").read_text()
    assert f"{evaluation['ate_rmse']:.4f} m" in text and f"{evaluation['rpe_rmse']:.4f} m" in text
    assert "built-in defaults" in text and "scenario: `default`" in text
    assert (demo_out / "recording.rrd").stat().st_size > 0


def test_demo_checks_the_scenario_before_rendering(tmp_path, capsys, monkeypatch):
    called = []
    monkeypatch.setattr(demo_cmd, "render", _fake_render(called))
    for argv, message in ((["--scenario", "no-such-scenario"], "no such scenario"),
                          (["--width", "4"], "--width must be in [16, 8192], got 4")):
        assert main(["demo", "--out", str(tmp_path / "o"), "--quiet", *argv]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and message in err
    assert called == [] and not (tmp_path / "o").exists()


def test_demo_interrupted_while_rendering_exits_130(tmp_path, capsys, monkeypatch):
    def interrupted(args, dataset_dir):
        raise KeyboardInterrupt

    monkeypatch.setattr(demo_cmd, "render", interrupted)
    assert main(["demo", "--out", str(tmp_path / "o"), "--quiet"]) == 130
    assert "interrupted while rendering" in capsys.readouterr().err


@pytest.mark.slow
def test_demo_interrupted_during_the_run_keeps_the_finished_outputs(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(demo_cmd, "render", _fake_render([]))
    original = MonocularVO.estimate  # the estimator's step, in the sequential and concurrent modes

    def estimate(self, frame_id, timestamp, image, *args):
        if frame_id == 30:
            raise KeyboardInterrupt
        return original(self, frame_id, timestamp, image, *args)

    monkeypatch.setattr(MonocularVO, "estimate", estimate)
    out = tmp_path / "o"
    assert main(["demo", "--out", str(out), "--quiet"]) == 130
    assert "interrupted" in capsys.readouterr().err
    assert len(read_tum(out / "run" / "trajectory.tum")) == 30
    summary = json.loads((out / "run" / "summary.json").read_text())
    assert summary["interrupted"] is True and summary["frames"] == 30
    assert "**interrupted**" in (out / "report.md").read_text()
    assert all(p.is_file() for p in _linked_images(out / "report.md"))


def test_run_without_ground_truth_writes_the_points_plot_and_says_why_not_the_others(tmp_path):
    dataset = tmp_path / "ds"
    shutil.copytree(SEQUENCES / "default", dataset)
    (dataset / "groundtruth.tum").unlink()
    shutil.rmtree(dataset / "mav0" / "state_groundtruth_estimate0", ignore_errors=True)
    out = tmp_path / "run"
    assert main(["run", str(dataset), "--out", str(out), "--quiet", "--max-frames", "30"]) == 0
    text = (out / "report.md").read_text()
    assert [p.name for p in _linked_images(out / "report.md")] == ["points.png"]
    assert "`trajectory.png` not written: no ground truth" in text
    assert not (out / "evaluation.json").exists()


def _diagnostics(n: int, with_lambda: bool):
    """Diagnostics rows, optionally with the future scale_drift_indicator column."""
    cls = FrameDiagnostics
    if with_lambda:
        cls = dataclasses.make_dataclass("WithLambda", [("scale_drift_indicator", float | None, None)],
                                         bases=(FrameDiagnostics,))
    rows = []
    for k in range(n):
        row = cls(0.05 * k, k, 0, "init" if k < 5 else "tracking", 100, 0 if k < 5 else 80, 100 if k < 5 else 20,
                  k % 10 == 0, -1.0, 10.0)
        if with_lambda:
            row.scale_drift_indicator = None if k < 10 else 1e3 * (1 + k)
        rows.append(row)
    return rows


def _circle(n: int, scale: float = 1.0):
    from planar_scene import look_down_pose

    t = 0.05 * np.arange(n)
    poses = np.array([look_down_pose([5 * np.cos(0.3 * s), 5 * np.sin(0.3 * s), 10 + 0.1 * s]) for s in t])
    est = poses.copy()
    est[:, :3, 3] *= scale
    return Trajectory(t, poses), Trajectory(t, est, np.zeros(n, np.int64))


def test_scale_plot_gets_a_lambda_panel_once_the_column_exists(tmp_path, monkeypatch):
    """With a ``scale_drift_indicator`` column (a field of the diagnostics rows) the scale plot
    gets a second panel drawing exactly the finite Λ values; without it, one panel."""
    from granite.evaluation import relative_scale_error
    from granite.visualization import report as module

    figures = []
    original = module.plot_scale
    monkeypatch.setattr(module, "plot_scale", lambda *a, **k: figures.append(original(*a, **k)) or figures[-1])
    gt, est = _circle(120, scale=0.3)
    report = write_plots(tmp_path, est, _diagnostics(120, True), [0.0, 0.5], gt, 1.0)
    assert set(report.plots) == {"trajectory.png", "translation_error.png", "points.png", "scale.png"}
    assert "Λ" in report.plots["scale.png"]
    (fig,) = figures
    assert len(fig.axes) == 2
    assert list(fig.axes[1].lines[0].get_ydata()) == pytest.approx([1e3 * (1 + k) for k in range(10, 120)])
    with_lambda = _check_png(tmp_path / "scale.png", 1210).shape[0]
    series = relative_scale_error(est, gt, 1.0)
    plain = original(tmp_path / "plain.png", series, np.zeros(series.timestamps.size, np.int64), None, None,
                     _diagnostics(120, False), 0.0)
    assert len(plain.axes) == 1 and _check_png(tmp_path / "plain.png", 1210).shape[0] < with_lambda


def test_trajectory_plot_draws_each_submap_aligned_on_the_ground_truth(tmp_path):
    """Two sub-maps with their own scale and origin, exact otherwise: after the per-sub-map
    Sim(3) alignment each drawn estimate curve lies on the ground truth, in both panels."""
    from granite.evaluation import ate
    from granite.visualization.report import plot_trajectory

    gt, est = _circle(120, scale=1.0)
    sub = (np.arange(120) >= 60).astype(np.int64)
    moved = est.poses.copy()
    moved[sub == 0, :3, 3] *= 0.3
    moved[sub == 1, :3, 3] = 2.0 * moved[sub == 1, :3, 3] + [4.0, -2.0, 1.0]
    est = Trajectory(est.timestamps, moved, sub)
    result = ate(est, gt, "sim3")
    fig = plot_trajectory(tmp_path / "t.png", result.aligned, gt, 0.0, result.scales, {})
    top, height = fig.axes[:2]
    for k in (0, 1):
        rows = sub == k
        (xy,) = [line for line in top.lines if line.get_label().startswith(f"estimate, sub-map {k}")]
        (tz,) = [line for line in height.lines if line.get_label().startswith(f"estimate, sub-map {k}")]
        assert np.allclose(np.c_[xy.get_xdata(), xy.get_ydata()], gt.positions[rows, :2], atol=1e-6)
        assert np.allclose(tz.get_ydata(), gt.positions[rows, 2], atol=1e-6)
        assert np.allclose(tz.get_xdata(), gt.timestamps[rows])
    labels = [line.get_label() for line in top.lines]
    assert "estimate, sub-map 0 (Sim(3) scale 3.33)" in labels and "estimate, sub-map 1 (Sim(3) scale 0.5)" in labels
    _check_png(tmp_path / "t.png", 1320)


def test_a_run_without_a_recording_does_not_load_rerun():
    """``granite run`` without ``--rerun`` (the command line with every subcommand's parser,
    the pipeline, run folder and report plots) never imports rerun, which would cost ~44 MB of
    resident memory; the lazy ``granite.visualization.RerunLogger`` still resolves when asked
    for."""
    import subprocess
    import sys

    code = ("import sys, granite.cli.main as m, granite.cli.run_cmd, granite.visualization.report, "
            "granite.visualization as v; m.build_parser(); "
            "print('rerun' in sys.modules, end=' '); v.RerunLogger; print('rerun' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "True"]
