"""`granite-sim view`: a rendered dataset logged to rerun, read back with rerun's own API."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import rerun as rr

from simulation.cli import main
from simulation.depth import read_depth

DATASET = Path(__file__).resolve().parents[1] / "assets" / "sequences" / "framedrop"


def _rows(path: Path) -> list[list[str]]:
    return [line.split(",") for line in path.read_text().splitlines() if not line.startswith("#")]


@pytest.mark.slow
def test_dataset_recording_holds_images_depth_and_ground_truth_poses(tmp_path):
    rrd = tmp_path / "framedrop.rrd"
    assert main(["view", str(DATASET), "--rerun", str(rrd), "--quiet"]) == 0
    table = rr.dataframe.load_recording(str(rrd)).view(index="frame", contents="/**").select().read_all()
    images = _rows(DATASET / "mav0" / "cam0" / "data.csv")
    frames = table.column("frame").to_pylist()
    assert sorted(frames) == list(range(len(images)))
    col = lambda name: table.column(name).to_pylist()  # noqa: E731
    present = lambda name: len(table) - table.column(name).null_count  # noqa: E731
    assert present("/world/camera/image:Blob") == len(images)  # the PNG files, as they are
    assert present("/world/camera/depth:ImageBuffer") == len(images)
    # The camera pose of frame k is the ground truth at its timestamp (independent reading of
    # the TUM file; rendered frames lie on ground-truth samples).
    gt = np.loadtxt(DATASET / "groundtruth.tum")
    positions = dict(zip(frames, col("/world/camera:Translation3D")))
    for k in (0, len(images) // 2, len(images) - 1):
        t = int(images[k][0]) * 1e-9
        row = gt[np.argmin(np.abs(gt[:, 0] - t))]
        np.testing.assert_allclose(positions[k][0], row[1:4], atol=1e-5)
    # The depth image is the depth map in metres (sky: 0).
    depth = read_depth(DATASET / "mav0" / "depth0" / "data" / images[3][1].strip())
    cell = table.column("/world/camera/depth:ImageBuffer")[frames.index(3)]
    logged = cell.values[0].values.to_numpy(zero_copy_only=False).astype(np.uint8)
    as_float = np.frombuffer(logged.tobytes(), dtype=np.float32).reshape(depth.shape)
    np.testing.assert_array_equal(as_float, np.where(np.isfinite(depth), depth, 0))
    static = rr.dataframe.load_recording(str(rrd)).view(index="frame", contents="/world/groundtruth/**")
    strip = static.select_static().read_all().column("/world/groundtruth:LineStrip3D").to_pylist()[0][0]
    assert len(strip) == len(gt)  # dropped frames keep their ground truth


def test_view_of_a_missing_dataset_is_one_clear_line(tmp_path, capsys):
    assert main(["view", str(tmp_path / "nope"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope" in err[0] and "Traceback" not in err[0]


def _first_frames(root: Path, n: int = 3) -> Path:
    """A copy of DATASET cut to its first ``n`` images and depth maps."""
    shutil.copytree(DATASET, root, ignore=shutil.ignore_patterns("data"))
    for sensor in ("cam0", "depth0"):
        folder = root / "mav0" / sensor
        lines = (DATASET / "mav0" / sensor / "data.csv").read_text().splitlines()
        rows = [line for line in lines if line.strip() and not line.startswith("#")][:n]
        (folder / "data.csv").write_text("\n".join([lines[0], *rows]) + "\n")
        (folder / "data").mkdir()
        for row in rows:
            name = row.split(",")[1].strip()
            shutil.copy(DATASET / "mav0" / sensor / "data" / name, folder / "data" / name)
    return root


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:200])


@pytest.mark.parametrize("target, message", [
    pytest.param(lambda t: Path("/proc/x.rrd"), "/proc/x.rrd: cannot be written",
                 marks=pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc")),
    (lambda t: t / "afile" / "x.rrd", "afile is not a folder"),
    (lambda t: t / "adir", "adir: is a folder, expected a file name"),
])
def test_unwritable_recording_is_one_line_before_any_work(tmp_path, capsys, target, message):
    (tmp_path / "afile").write_text("a file")
    (tmp_path / "adir").mkdir()
    before = sorted(tmp_path.rglob("*"))
    assert main(["view", str(DATASET), "--rerun", str(target(tmp_path)), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("granite-sim view: error: ") and message in err, err
    assert sorted(tmp_path.rglob("*")) == before


def test_truncated_depth_map_leaves_no_partial_recording(tmp_path, capsys):
    dataset = _first_frames(tmp_path / "ds")
    depth = sorted((dataset / "mav0" / "depth0" / "data").iterdir())[1]
    _truncate(depth)
    out = tmp_path / "out"
    out.mkdir()
    assert main(["view", str(dataset), "--rerun", str(out / "view.rrd"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("granite-sim view: error: ") and depth.name in err, err
    assert not any(out.iterdir())  # neither view.rrd nor a temporary file


def test_unreadable_image_is_a_warning_line(tmp_path, capsys):
    dataset = _first_frames(tmp_path / "ds")
    image = dataset / "mav0" / "cam0" / "data" / _rows(dataset / "mav0" / "cam0" / "data.csv")[1][1]
    _truncate(image)
    rrd = tmp_path / "view.rrd"
    assert main(["view", str(dataset), "--rerun", str(rrd), "--no-depth", "--quiet"]) == 0
    out, err = capsys.readouterr()
    assert err.count("\n") == 1 and err.startswith("granite-sim view: warning: frame 1: image skipped: ")
    assert str(image) in err and "3 frames, 2 images" in out and rrd.is_file()
