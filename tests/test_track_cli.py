"""``granite track``: output formats against the known image motion, unusable frames, and user
errors ending in exit status 2 with one error line."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from granite.cli import main as cli_main
from granite.optical_flow.synthetic import apply_affine, similarity, textured_image, warp

W, H = 320, 240
N_FRAMES = 6
BLANK = 3  # index of a blank frame


def affine_of(k: int) -> np.ndarray:
    """Frame k shows the big texture mapped by this affine."""
    return similarity(-60.0 - 3.0 * k, -50.0 - 2.0 * k, np.radians(0.4 * k), 1.0, (200.0, 170.0))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """A small EuRoC-layout sequence; frame BLANK is constant, frame 5 is corrupt."""
    root = tmp_path_factory.mktemp("track") / "seq"
    data = root / "mav0" / "cam0" / "data"
    data.mkdir(parents=True)
    big = textured_image(400, 500, seed=11)
    lines = ["#timestamp [ns],filename"]
    for k in range(N_FRAMES):
        ns = 1_000_000_000 + 50_000_000 * k
        img = warp(big, affine_of(k), (W, H))
        if k == BLANK:
            img[:] = 90
        if k == 5:
            (data / f"{ns}.png").write_bytes(b"not a png")
        else:
            cv2.imwrite(str(data / f"{ns}.png"), img)
        lines.append(f"{ns},{ns}.png")
    (root / "mav0" / "cam0" / "data.csv").write_text("\n".join(lines) + "\n")
    return root


@pytest.fixture(autouse=True)
def registered(monkeypatch):
    """Register the subcommand for the test if the lead has not wired it yet."""
    if "track" not in cli_main.SUBCOMMANDS:
        monkeypatch.setattr(cli_main, "SUBCOMMANDS", (*cli_main.SUBCOMMANDS, "track"))


def run_cli(capsys, *args) -> tuple[int, str, str]:
    code = cli_main.main(["track", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def read_csv(path: Path) -> dict[str, np.ndarray]:
    with path.open(newline="") as handle:
        reader = csv.reader(handle)
        header = next(reader)
        rows = list(reader)
    assert header == ["timestamp", "id", "x", "y", "level"]
    cols = list(zip(*rows)) if rows else [()] * 5
    return {
        "timestamp": np.array(cols[0], dtype=float), "id": np.array(cols[1], dtype=int),
        "x": np.array(cols[2], dtype=float), "y": np.array(cols[3], dtype=float),
        "level": np.array(cols[4], dtype=int),
    }


def test_csv_tracks_follow_the_known_motion(capsys, dataset, tmp_path):
    out_path = tmp_path / "tracks.csv"
    code, out, err = run_cli(capsys, dataset, "--out", out_path)
    assert code == 0, err
    assert "wrote" in out and "6 frames (2 rejected)" in out
    warnings = [line for line in err.splitlines() if "granite track: warning" in line]
    assert len(warnings) == 2 and "blank" in warnings[0] and "frame 5" in warnings[1]
    t = read_csv(out_path)
    stamps = 1.0 + 0.05 * np.arange(N_FRAMES)
    present = np.unique(t["timestamp"])
    np.testing.assert_allclose(present, stamps[[0, 1, 2, 4]], atol=1e-9)
    assert len(np.unique(np.c_[t["timestamp"], t["id"]], axis=0)) == len(t["id"])
    # Every track seen in two frames moved as the images did.
    errors = []
    for i, j in [(0, 1), (1, 2), (2, 4)]:
        a, b = t["timestamp"] == stamps[i], t["timestamp"] == stamps[j]
        ids, ia, ib = np.intersect1d(t["id"][a], t["id"][b], return_indices=True)
        assert len(ids) > 40
        pa = np.c_[t["x"][a], t["y"][a]][ia]
        pb = np.c_[t["x"][b], t["y"][b]][ib]
        back = apply_affine(cv2.invertAffineTransform(affine_of(i)), pa)
        errors.append(np.linalg.norm(pb - apply_affine(affine_of(j), back), axis=1))
        np.testing.assert_array_equal(t["level"][a][ia], t["level"][b][ib])
    assert np.median(np.concatenate(errors)) < 0.1
    assert np.any(t["level"] == 0) and np.any(t["level"] > 0)  # multi-level detection
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # atomic write


def test_npz_holds_the_same_tracks_and_frame_info(capsys, dataset, tmp_path):
    code, _, err = run_cli(capsys, dataset, "--out", tmp_path / "t.csv", "--quiet")
    assert code == 0 and "warning" in err
    code, _, _ = run_cli(capsys, dataset, "--out", tmp_path / "t.npz", "--quiet")
    assert code == 0
    c = read_csv(tmp_path / "t.csv")
    with np.load(tmp_path / "t.npz") as z:
        for key in ("timestamp", "id", "level"):
            np.testing.assert_array_equal(z[key], c[key]) if key != "timestamp" else \
                np.testing.assert_allclose(z[key], c[key], atol=1e-9)
        np.testing.assert_allclose(z["x"], c["x"], atol=5e-5)
        np.testing.assert_allclose(z["y"], c["y"], atol=5e-5)
        np.testing.assert_array_equal(z["frame_rejected"], [False, False, False, True, False, True])
        counts = [np.sum(np.isclose(c["timestamp"], s)) for s in z["frame_timestamp"]]
        np.testing.assert_array_equal(z["frame_tracks"], counts)
        assert z["frame_ms"].shape == (N_FRAMES, 3)
        assert json.loads(str(z["config"]))["levels"] == 6


def test_finest_level_only_and_config_file(capsys, dataset, tmp_path):
    code, _, _ = run_cli(capsys, dataset, "--out", tmp_path / "a.csv", "--finest-level-only", "--quiet")
    assert code == 0 and np.all(read_csv(tmp_path / "a.csv")["level"] == 0)
    cfg = tmp_path / "flow.toml"
    cfg.write_text("[optical_flow]\nlevels = 4\ngrid_size = 80\n")
    code, _, _ = run_cli(capsys, dataset, "--out", tmp_path / "b.csv", "--config", cfg,
                         "--stop", 1, "--quiet")
    first = read_csv(tmp_path / "b.csv")
    assert code == 0 and np.all(first["level"] <= 2)
    assert 0 < np.sum(first["level"] == 0) <= (W // 80) * (H // 80)  # the 80 px grid


@pytest.mark.parametrize(
    "make_args, message",
    [
        (lambda d, t: [d, "--out", t / "x.txt"], "unknown output format"),
        (lambda d, t: [t / "missing", "--out", t / "x.csv"], "not found"),
        (lambda d, t: [d, "--out", t / "x.csv", "--levels", "0"], "levels"),
        (lambda d, t: [d, "--out", t / "x.csv", "--config", t / "bad.toml"], "unknown key"),
        (lambda d, t: [d, "--out", t / "x.csv", "--config", t / "typed.toml"],
         "typed.toml: [optical_flow] grid_size: must be an integer, got '40'"),
        (lambda d, t: [d, "--out", t / "bad.toml" / "x.csv"], "cannot be created"),
    ],
)
def test_user_errors_exit_2_with_one_line(capsys, dataset, tmp_path, make_args, message):
    (tmp_path / "bad.toml").write_text("levls = 3\n")
    (tmp_path / "typed.toml").write_text('[optical_flow]\ngrid_size = "40"\n')
    code, out, err = run_cli(capsys, *make_args(dataset, tmp_path))
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("granite track: error:") and message in err
    assert not (tmp_path / "x.csv").exists()


@pytest.mark.parametrize(
    "frames, message",
    [
        (["--start", "-1"], "argument --start: must be at least 0: '-1'"),
        (["--stop", "0"], "argument --stop: must be at least 1: '0'"),
        (["--start", "4", "--stop", "2"], "--start 4 must be less than --stop 2"),
        (["--start", str(N_FRAMES)], f"--start {N_FRAMES} is past the last frame (the dataset has {N_FRAMES} frames"),
        (["--start", "100", "--stop", "200"], "--start 100 is past the last frame"),
    ],
)
def test_empty_or_negative_frame_range_exits_2_before_any_work(capsys, dataset, tmp_path, frames, message):
    try:
        code = cli_main.main(["track", str(dataset), "--out", str(tmp_path / "x.csv"), *frames])
    except SystemExit as exit_:  # argparse errors
        code = exit_.code
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("granite track: error:") and message in err
    assert not (tmp_path / "x.csv").exists()


@pytest.mark.parametrize("cached", [False, True])
def test_a_first_run_says_that_numba_compiles(capsys, monkeypatch, dataset, tmp_path, cached):
    import granite._numba_cache

    monkeypatch.setattr(granite._numba_cache, "has_cached_kernels", lambda cache_dir=None, kernels=(): cached)
    code, _, err = run_cli(capsys, dataset, "--out", tmp_path / "tracks.csv")
    assert code == 0, err
    notices = [line for line in err.splitlines() if "numba compiles the kernels" in line]
    assert len(notices) == (0 if cached else 1)
    if notices:
        assert notices[0].startswith("granite track: first run")
