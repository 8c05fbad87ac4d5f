"""``granite eval``: table and JSON output, ground-truth format detection, and every bad input
ending in exit status 2 with exactly one error line naming the file (and line)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from granite.cli.main import main
from granite.io import Calibration, write_calibration, write_euroc_groundtruth, write_tum
from granite.trajectory import Trajectory

ROOT = Path(__file__).resolve().parents[1]


def helix(t: np.ndarray) -> np.ndarray:
    """Camera poses on a helix (radius 2 m, 0.5 rad/s, climbing 0.1 m/s), yawing along."""
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(np.c_[0 * t, 0 * t, 0.5 * t]).as_matrix()
    poses[:, :3, 3] = np.c_[2 * np.cos(0.5 * t), 2 * np.sin(0.5 * t), 0.1 * t]
    return poses


@pytest.fixture()
def files(tmp_path: Path) -> dict[str, Path]:
    t = np.arange(0.0, 20.0 + 1e-9, 0.1)
    gt = Trajectory(t, helix(t))
    # estimate: the ground truth at half scale, shifted, with a restart at t = 12 s
    est_poses = helix(t)
    est_poses[:, :3, 3] = 0.5 * est_poses[:, :3, 3] + np.array([1.0, 2.0, 3.0])
    sub = (t >= 12.0 - 1e-9).astype(int)
    write_tum(tmp_path / "gt.tum", gt)
    write_tum(tmp_path / "est.tum", Trajectory(t, est_poses, sub))
    write_euroc_groundtruth(tmp_path / "gt.csv", gt)
    return {"gt": tmp_path / "gt.tum", "est": tmp_path / "est.tum", "csv": tmp_path / "gt.csv"}


def run_cli(capsys, *args: str) -> tuple[int, str, str]:
    code = main(["eval", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def test_json_output(capsys, files) -> None:
    code, out, err = run_cli(capsys, "--est", files["est"], "--gt", files["gt"], "--json", "--delta", "4")
    assert code == 0 and err == ""
    result = json.loads(out)  # exactly one JSON object
    assert isinstance(result, dict) and out.strip().count("\n") == 0
    assert result["ate_rmse"] < 1e-9 and result["rpe_rmse"] < 1e-9
    assert result["restarts"] == 1
    # runs 0 .. 11.9 s and 12 .. 20 s; the longer one over the 20 s of the estimate
    assert result["tracking_percentage"] == pytest.approx(100 * 11.9 / 20.0)
    assert result["num_poses"] == 201
    # pairs: t = 4.0 .. 11.9 (80) and t = 16.0 .. 20.0 (41); t = 12.0 .. 15.9 spans the restart
    assert result["num_rpe_pairs"] == 121 and result["rpe_skipped_submap"] == 40
    assert result["path_length"] == pytest.approx(20 * math.hypot(1.0, 0.1), rel=1e-3)
    assert result["submap_scales"] == {"0": pytest.approx(2.0), "1": pytest.approx(2.0)}
    assert result["align"] == "sim3" and result["delta"] == 4.0


def test_table_output_and_euroc_ground_truth(capsys, files) -> None:
    code, out, err = run_cli(capsys, "--est", files["est"], "--gt", files["csv"], "--delta", "2",
                             "--align", "se3")
    assert code == 0 and err == ""
    assert "ATE RMSE (se3, per sub-map)" in out and "RPE RMSE (delta 2 s)" in out
    assert "tracking percentage" in out and "restarts" in out
    # se3 cannot undo the half scale: a clearly positive ATE
    ate_line = next(line for line in out.splitlines() if line.startswith("ATE RMSE"))
    assert float(ate_line.split()[-2]) > 0.1


def test_euroc_ground_truth_with_calib(capsys, tmp_path, files) -> None:
    T_bc = np.eye(4)
    T_bc[:3, 3] = [0.3, 0.0, 0.0]
    t = np.arange(0.0, 20.0 + 1e-9, 0.1)
    body = Trajectory(t, helix(t) @ np.linalg.inv(T_bc))  # so that body @ T_bc = camera = helix
    write_euroc_groundtruth(tmp_path / "body.csv", body)
    write_calibration(tmp_path / "calib.json",
                      Calibration("pinhole", {"fx": 1, "fy": 1, "cx": 0, "cy": 0}, 4, 4, T_bc))
    args = ["--est", files["est"], "--gt", tmp_path / "body.csv", "--json"]
    code, out, _ = run_cli(capsys, *args, "--calib", tmp_path / "calib.json")
    assert code == 0 and json.loads(out)["ate_rmse"] < 1e-9
    code, out, _ = run_cli(capsys, *args)  # without the lever arm the error is visible
    assert code == 0 and json.loads(out)["ate_rmse"] > 0.01


GOOD = "0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n"


@pytest.mark.parametrize(
    "name, text, line, message",
    [
        ("malformed", GOOD + "2 1 0 0 zero 0 0 1\n", 3, "is not a number"),
        ("columns", GOOD + "2 1 0 0 0 0 1\n", 3, "columns"),
        ("unsorted", GOOD + "0.5 1 0 0 0 0 0 1\n", 3, "unsorted"),
        ("duplicate", GOOD + "1 2 0 0 0 0 0 1\n", 3, "duplicate"),
        ("nan", GOOD + "2 nan 0 0 0 0 0 1\n", 3, "not finite"),
        ("quaternion", GOOD + "2 1 0 0 0 0 0 3\n", 3, "quaternion norm"),
        ("empty", "# nothing here\n", None, "empty trajectory"),
    ],
)
@pytest.mark.parametrize("which", ["est", "gt"])
def test_bad_trajectory_files(capsys, tmp_path, files, which, name, text, line, message) -> None:
    bad = tmp_path / f"{name}.tum"
    bad.write_text(text)
    args = {"est": files["est"], "gt": files["gt"], which: bad}
    code, out, err = run_cli(capsys, "--est", args["est"], "--gt", args["gt"])
    assert code == 2 and out == ""
    assert_one_error_line(err, bad, line, message)


def assert_one_error_line(err: str, path: Path, line: int | None, message: str) -> None:
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("granite eval: error: ")
    where = f"{path}:{line}: " if line is not None else f"{path}: "
    assert where in lines[0] and message in lines[0]
    assert "Traceback" not in err


def test_missing_file(capsys, tmp_path, files) -> None:
    code, out, err = run_cli(capsys, "--est", tmp_path / "nope.tum", "--gt", files["gt"])
    assert code == 2 and out == ""
    assert_one_error_line(err, tmp_path / "nope.tum", None, "not found")


def test_no_time_overlap(capsys, tmp_path, files) -> None:
    late = tmp_path / "late.tum"
    late.write_text("100 0 0 0 0 0 0 1\n101 1 0 0 0 0 0 1\n102 1 1 0 0 0 0 1\n")
    code, _, err = run_cli(capsys, "--est", late, "--gt", files["gt"])
    assert code == 2
    assert_one_error_line(err, late, None, "does not overlap the ground truth")
    assert err.rstrip().endswith("in time")


def test_bad_euroc_ground_truth(capsys, tmp_path, files) -> None:
    bad = tmp_path / "gt.csv"
    bad.write_text("#timestamp,x,y,z,qw,qx,qy,qz\n1000,0,0,0,1,0,0,0\n2000,0,0,0,1,0,0,x\n")
    code, _, err = run_cli(capsys, "--est", files["est"], "--gt", bad)
    assert code == 2
    assert_one_error_line(err, bad, 3, "is not a number")


def test_calibration_missing_field(capsys, tmp_path, files) -> None:
    calib = tmp_path / "calib.json"
    intrinsics = [{"camera_type": "pinhole", "intrinsics": {"fx": 1, "fy": 1, "cx": 0}}]
    calib.write_text(json.dumps({"value0": {"intrinsics": intrinsics, "resolution": [[4, 4]]}}))
    code, _, err = run_cli(capsys, "--est", files["est"], "--gt", files["csv"], "--calib", calib)
    assert code == 2
    assert_one_error_line(err, calib, None, "missing field value0.intrinsics[0].intrinsics.cy")


def test_bad_delta_is_a_usage_error(capsys, files) -> None:
    with pytest.raises(SystemExit) as info:
        main(["eval", "--est", str(files["est"]), "--gt", str(files["gt"]), "--delta", "-1"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "positive number of seconds" in err and err.count("\n") == 1


def test_align_frames_and_the_fixed_scale_rpe(capsys, files) -> None:
    """The half-scale copy aligned on each sub-map's first 100 poses (sub-map 1 has 81: all of
    them) is exact, and so is its RPE with the alignment scale; a length error would show."""
    code, out, err = run_cli(capsys, "--est", files["est"], "--gt", files["gt"], "--json", "--align-frames", "100")
    assert code == 0 and err == ""
    result = json.loads(out)
    assert result["align_frames"] == 100 and result["submap_scales"] == {"0": pytest.approx(2.0), "1": pytest.approx(2.0)}
    assert result["ate_rmse"] < 1e-9 and result["rpe_fixed_scale_rmse"] < 1e-9
    assert result["num_rpe_fixed_scale_pairs"] == result["num_rpe_pairs"]
    code, out, _ = run_cli(capsys, "--est", files["est"], "--gt", files["gt"], "--align-frames", "100")
    assert "aligned on the first 100 poses" in out and "RPE RMSE, fixed scale" in out
    with pytest.raises(SystemExit) as info:
        main(["eval", "--est", str(files["est"]), "--gt", str(files["gt"]), "--align-frames", "2"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "at least 3 poses" in err and err.count("\n") == 1


@pytest.mark.slow
def test_subprocess_error_has_no_traceback(tmp_path, files) -> None:
    bad = tmp_path / "bad.tum"
    bad.write_text(GOOD + "0.5 1 0 0 0 0 0 1\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(
        [sys.executable, "-m", "granite.cli.main", "eval",
         "--est", str(bad), "--gt", str(files["gt"])],
        capture_output=True, text=True, cwd=ROOT, env=env, timeout=120,
    )
    assert proc.returncode == 2 and proc.stdout == ""
    assert_one_error_line(proc.stderr, bad, 3, "unsorted")
