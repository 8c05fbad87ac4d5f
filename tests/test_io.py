"""File formats: round trips, hand-written files with known content, every bad input, and
open_dataset on tiny generated folders of each layout."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from granite.errors import InputError
from granite.io import (
    Calibration,
    atomic_path,
    atomic_write_text,
    open_dataset,
    read_calibration,
    read_euroc_groundtruth,
    read_image,
    read_sensor_yaml,
    read_trajectory,
    read_tum,
    write_calibration,
    write_euroc_groundtruth,
    write_euroc_image_list,
    write_tum,
)
from granite.trajectory import Trajectory


def random_trajectory(n: int, seed: int, submap: bool = False, t0: float = 1.4e9) -> Trajectory:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.normal(scale=10.0, size=(n, 3))
    t = t0 + np.cumsum(rng.uniform(0.01, 0.1, size=n))
    return Trajectory(t, poses, np.repeat(np.arange(3), -(-n // 3))[:n] if submap else None)


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


# --------------------------------------------------------------------------- Trajectory


def test_trajectory_validation_and_helpers() -> None:
    t = np.array([0.0, 1.0, 2.0, 3.0])
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, 0, 3] = [0.0, 1.0, 3.0, 6.0]
    traj = Trajectory(t, poses, np.array([0, 0, 1, 1]))
    assert len(traj) == 4
    assert np.array_equal(traj.positions[:, 0], [0, 1, 3, 6])
    assert traj.path_length() == pytest.approx(1.0 + 3.0)  # the jump 1 -> 3 joins two sub-maps
    assert Trajectory(t, poses).path_length() == pytest.approx(6.0)
    assert traj.runs() == [(0, 2), (2, 4)]
    assert not traj.timestamps.flags.writeable
    with pytest.raises(ValueError):
        Trajectory(np.array([0.0, 0.0, 1.0, 2.0]), poses)
    with pytest.raises(ValueError):
        Trajectory(t, poses[:3])
    bad = poses.copy()
    bad[1, :3, :3] *= 2.0
    with pytest.raises(ValueError):
        Trajectory(t, bad)
    with pytest.raises(ValueError):
        Trajectory(t, poses, np.array([0.0, 0.5, 1.0, 1.0]))


# --------------------------------------------------------------------------- TUM


@pytest.mark.parametrize("submap", [False, True])
def test_tum_round_trip(tmp_path: Path, submap: bool) -> None:
    traj = random_trajectory(50, seed=3, submap=submap)
    write_tum(tmp_path / "t.tum", traj)
    rows = [r for r in (tmp_path / "t.tum").read_text().splitlines() if not r.startswith("#")]
    assert {len(r.split()) for r in rows} == {9 if submap else 8}
    back = read_tum(tmp_path / "t.tum")
    assert np.array_equal(back.timestamps, traj.timestamps)  # full precision
    assert np.allclose(back.poses, traj.poses, atol=1e-12)
    if submap:
        assert np.array_equal(back.submap, traj.submap)
    else:
        assert back.submap is None


def test_tum_known_content(tmp_path: Path) -> None:
    c = math.sqrt(0.5)
    text = f"# comment\n\n1.5 1 2 3 0 0 {c} {c}\n  2.5 0 0 0 0 0 0 1.0005\n"
    path = write(tmp_path / "t.txt", text)
    traj = read_tum(path)
    assert np.array_equal(traj.timestamps, [1.5, 2.5])
    assert np.allclose(traj.poses[0, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]])  # 90 deg about z
    assert np.array_equal(traj.positions[0], [1, 2, 3])
    assert np.allclose(traj.poses[1], np.eye(4))  # |q| = 1.0005 is normalised


BAD_TUM = {
    "non-numeric": ("0 0 0 0 0 0 0 1\n1 0 x 0 0 0 0 1\n", 2, "is not a number"),
    "nan": ("0 0 0 0 0 0 0 1\n1 0 nan 0 0 0 0 1\n", 2, "not finite"),
    "inf": ("0 0 0 0 0 0 0 1\n1 0 0 inf 0 0 0 1\n", 2, "not finite"),
    "too few columns": ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n", 2, "columns"),
    "mixed 8/9": ("0 0 0 0 0 0 0 1 0\n1 0 0 0 0 0 0 1\n", 2, "columns"),
    "10 columns": ("# h\n0 0 0 0 0 0 0 1 0 7\n", 2, "columns"),
    "unsorted": ("0 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", 3, "unsorted"),
    "duplicate": ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n\n1 0 0 0 0 0 0 1\n", 4, "duplicate"),
    "bad quaternion": ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1.1\n", 2, "quaternion norm"),
    "zero quaternion": ("0 0 0 0 0 0 0 0\n", 1, "quaternion norm"),
    "fractional submap": ("0 0 0 0 0 0 0 1 0.5\n", 1, "submap"),
}


@pytest.mark.parametrize("case", sorted(BAD_TUM))
def test_tum_bad_input(tmp_path: Path, case: str) -> None:
    text, line, message = BAD_TUM[case]
    path = write(tmp_path / "bad.tum", text)
    with pytest.raises(InputError, match=message) as info:
        read_tum(path)
    assert info.value.path == path and info.value.line == line
    assert str(info.value).startswith(f"{path}:{line}: ")


def test_tum_missing_and_empty(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found") as info:
        read_tum(tmp_path / "nope.tum")
    assert info.value.path == tmp_path / "nope.tum"
    with pytest.raises(InputError, match="empty trajectory"):
        read_tum(write(tmp_path / "e.tum", "# only a header\n\n"))
    with pytest.raises(InputError, match="directory"):
        read_tum(tmp_path)


# --------------------------------------------------------------------------- EuRoC


def test_euroc_groundtruth_round_trip_and_extrinsics(tmp_path: Path) -> None:
    traj = random_trajectory(40, seed=5)
    write_euroc_groundtruth(tmp_path / "gt.csv", traj)
    back = read_euroc_groundtruth(tmp_path / "gt.csv")
    assert np.allclose(back.timestamps, traj.timestamps, atol=1e-6)
    assert np.allclose(back.poses, traj.poses, atol=1e-12)
    T_bc = np.eye(4)
    T_bc[:3, :3] = Rotation.from_euler("xyz", [0.1, 0.2, 0.3]).as_matrix()
    T_bc[:3, 3] = [0.05, -0.02, 0.1]
    cam = read_euroc_groundtruth(tmp_path / "gt.csv", T_bc)
    assert np.allclose(cam.poses, traj.poses @ T_bc, atol=1e-12)
    assert read_trajectory(tmp_path / "gt.csv").poses.shape == (40, 4, 4)  # auto-detected


def test_euroc_groundtruth_known_content(tmp_path: Path) -> None:
    c = math.sqrt(0.5)
    header = (
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], "
        "q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], v_x\n"
    )
    rows = f"1403636579763555584,1,2,3,{c},0,0,{c},0.5\n1403636579813555456,1,2,3,1,0,0,0,0\n"
    path = write(tmp_path / "data.csv", header + rows)
    traj = read_euroc_groundtruth(path)
    assert traj.timestamps[0] == pytest.approx(1403636579.763555584, abs=1e-6)
    assert traj.timestamps[1] - traj.timestamps[0] == pytest.approx(0.049999872, abs=1e-6)
    assert np.allclose(traj.poses[0, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]])  # q wxyz order
    assert np.array_equal(traj.positions[0], [1, 2, 3])


@pytest.mark.parametrize(
    "rows, line, message",
    [
        ("1,0,0,0,1,0,0\n", 2, "at least 8"),
        ("1,0,0,0,1,0,0,0\n2,0,0,0,1,0,0\n", 3, "columns"),
        ("1.5,0,0,0,1,0,0,0\n", 2, "not an integer"),
        ("1,0,0,0,1,0,0,0,abc\n", 2, "column 9"),
        ("2,0,0,0,1,0,0,0\n1,0,0,0,1,0,0,0\n", 3, "unsorted"),
        ("1,0,0,nan,1,0,0,0\n", 2, "not finite"),
    ],
)
def test_euroc_groundtruth_bad_input(tmp_path: Path, rows: str, line: int, message: str) -> None:
    path = write(tmp_path / "gt.csv", "#timestamp,x,y,z,qw,qx,qy,qz\n" + rows)
    with pytest.raises(InputError, match=message) as info:
        read_euroc_groundtruth(path)
    assert info.value.path == path and info.value.line == line


EUROC_SENSOR_YAML = """\
# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""


def test_sensor_yaml(tmp_path: Path) -> None:
    info = read_sensor_yaml(write(tmp_path / "sensor.yaml", EUROC_SENSOR_YAML))
    assert info.resolution == (752, 480)
    assert info.intrinsics == [458.654, 457.296, 367.215, 248.375]
    assert info.camera_model == "pinhole" and info.distortion_model == "radial-tangential"
    assert info.distortion_coefficients[3] == 1.76187114e-05
    assert info.T_BS[1, 3] == -0.064676986768 and info.T_BS[2, 0] == -0.0257744366974
    assert np.array_equal(info.T_BS[3], [0, 0, 0, 1])


# --------------------------------------------------------------------------- calibration


CALIBS = [
    Calibration("pinhole", {"fx": 500.0, "fy": 501.0, "cx": 320.5, "cy": 240.25}, 640, 480),
    Calibration("kb4", {"fx": 380.0, "fy": 381.0, "cx": 510.0, "cy": 512.0,
                        "k1": 0.01, "k2": -0.002, "k3": 0.0003, "k4": -1e-5}, 1024, 1024),
    Calibration("ds", {"fx": 349.7, "fy": 348.7, "cx": 365.9, "cy": 249.3,
                       "xi": -0.24, "alpha": 0.567}, 752, 480),
]


@pytest.mark.parametrize("calib", CALIBS, ids=lambda c: c.camera_type)
def test_calibration_round_trip(tmp_path: Path, calib: Calibration) -> None:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [90, 1, -2], degrees=True).as_matrix()
    T[:3, 3] = [0.1, -0.2, 0.3]
    calib = Calibration(calib.camera_type, calib.intrinsics, calib.width, calib.height, T)
    write_calibration(tmp_path / "calib.json", calib)
    data = json.loads((tmp_path / "calib.json").read_text())["value0"]
    assert data["intrinsics"][0]["camera_type"] == calib.camera_type
    assert data["resolution"] == [[calib.width, calib.height]]
    assert len(data["calib_accel_bias"]) == 9 and len(data["calib_gyro_bias"]) == 12
    assert data["cam_time_offset_ns"] == 0 and data["vignette"] == []
    back = read_calibration(tmp_path / "calib.json")
    assert back.camera_type == calib.camera_type and back.intrinsics == calib.intrinsics
    assert (back.width, back.height) == (calib.width, calib.height)
    assert np.allclose(back.T_imu_cam, T, atol=1e-12)
    camera = back.camera()
    assert (camera.width, camera.height) == (calib.width, calib.height)


def basalt_json(**overrides) -> dict:
    value0 = {
        "T_imu_cam": [{"px": 1.0, "py": 2.0, "pz": 3.0, "qx": 0.0, "qy": 0.0,
                       "qz": math.sqrt(0.5), "qw": math.sqrt(0.5)}],
        "intrinsics": [{"camera_type": "pinhole", "intrinsics": {
            "fx": 458.654, "fy": 457.296, "cx": 367.215, "cy": 248.375}}],
        "resolution": [[752, 480]],
        "vignette": [],
        "mocap_time_offset_ns": 0,
    }
    value0.update(overrides)
    return {"value0": value0}


def test_calibration_known_content(tmp_path: Path) -> None:
    path = write(tmp_path / "c.json", json.dumps(basalt_json(), indent=2))
    calib = read_calibration(path)
    assert calib.intrinsics == {"fx": 458.654, "fy": 457.296, "cx": 367.215, "cy": 248.375}
    assert np.allclose(calib.T_imu_cam[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    assert np.array_equal(calib.T_imu_cam[:3, 3], [1, 2, 3])
    no_T = basalt_json()
    del no_T["value0"]["T_imu_cam"]
    calib = read_calibration(write(tmp_path / "d.json", json.dumps(no_T)))
    assert np.array_equal(calib.T_imu_cam, np.eye(4))


def _drop_fx(d):
    del d["value0"]["intrinsics"][0]["intrinsics"]["fx"]
    return d


@pytest.mark.parametrize(
    "data, message",
    [
        (_drop_fx(basalt_json()), "missing field value0.intrinsics[0].intrinsics.fx"),
        (basalt_json(intrinsics=[]), "missing field value0.intrinsics[0]"),
        ({"value1": {}}, "missing field .value0"),
        (basalt_json(resolution=[]), "missing field value0.resolution[0]"),
        (basalt_json(resolution=[[752]]), "value0.resolution[0] must be"),
        (basalt_json(intrinsics=[{"camera_type": "pinhole",
                                  "intrinsics": {"fx": -1, "fy": 1, "cx": 0, "cy": 0}}]),
         "value0.intrinsics[0]: "),
        (basalt_json(intrinsics=[{"camera_type": "eucm", "intrinsics": {}}]), "unsupported 'eucm'"),
        (basalt_json(T_imu_cam=[{"px": 0, "py": 0, "pz": 0, "qx": 0, "qy": 0, "qz": 0}]),
         "missing field value0.T_imu_cam[0].qw"),
        (basalt_json(T_imu_cam=[{"px": 0, "py": 0, "pz": 0, "qx": 0, "qy": 0, "qz": 0, "qw": 2}]),
         "quaternion norm"),
    ],
)
def test_calibration_bad_input(tmp_path: Path, data: dict, message: str) -> None:
    path = write(tmp_path / "calib.json", json.dumps(data))
    with pytest.raises(InputError) as info:
        read_calibration(path)
    assert message in info.value.message
    assert info.value.path == path


def test_calibration_invalid_json_and_missing(tmp_path: Path) -> None:
    path = write(tmp_path / "c.json", '{\n  "value0": {\n    "intrinsics": [,]\n}}\n')
    with pytest.raises(InputError, match="invalid JSON") as info:
        read_calibration(path)
    assert info.value.line == 3
    with pytest.raises(InputError, match="not found"):
        read_calibration(tmp_path / "none.json")


def test_calibration_top_level_not_an_object_is_one_clear_line(tmp_path: Path, capsys) -> None:
    from granite.cli.main import main

    path = write(tmp_path / "calib.json", "[1]\n")
    with pytest.raises(InputError, match="top level must be a JSON object"):
        read_calibration(path)
    root = tmp_path / "seq"
    make_euroc(root)
    assert main(["run", str(root), "--calib", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{path}: top level must be a JSON object" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- atomic, images


def test_atomic_writes(tmp_path: Path) -> None:
    target = tmp_path / "out.txt"
    atomic_write_text(target, "one\n")
    atomic_write_text(target, "two\n")
    assert target.read_text() == "two\n"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("partial")
            raise RuntimeError("crash while writing")
    assert target.read_text() == "two\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]  # no temp file left
    with atomic_path(tmp_path / "img.png") as tmp:
        assert tmp.suffix == ".png" and tmp.parent == tmp_path
        assert cv2.imwrite(str(tmp), np.zeros((4, 4), np.uint8))
    assert read_image(tmp_path / "img.png").shape == (4, 4)


def test_read_image(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "g8.png"), np.full((3, 5), 7, np.uint8))
    cv2.imwrite(str(tmp_path / "g16.png"), np.full((3, 5), 40000, np.uint16))
    bgr = np.zeros((3, 5, 3), np.uint8)
    bgr[..., 2] = 255  # pure red: gray = 0.299 * 255
    cv2.imwrite(str(tmp_path / "c.png"), bgr)
    g8, g16, gray = (read_image(tmp_path / n) for n in ("g8.png", "g16.png", "c.png"))
    assert g8.dtype == np.uint8 and g8.shape == (3, 5) and g8[0, 0] == 7
    assert g16.dtype == np.uint16 and g16[0, 0] == 40000
    assert gray.shape == (3, 5) and gray[0, 0] == round(0.299 * 255)
    with pytest.raises(InputError, match="not found"):
        read_image(tmp_path / "missing.png")
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\nthis is not a png")
    (tmp_path / "cut.png").write_bytes((tmp_path / "g16.png").read_bytes()[:-20])
    (tmp_path / "junk.png").write_bytes(b"junk")
    (tmp_path / "empty.png").write_bytes(b"")
    for name in ("bad.png", "cut.png", "junk.png", "empty.png"):
        with pytest.raises(InputError, match="cannot decode|empty image"):
            read_image(tmp_path / name)


# --------------------------------------------------------------------------- datasets


def save_png(path: Path, value: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.full((6, 8), value, np.uint8))


def make_euroc(root: Path, n: int = 5, corrupt: int | None = None) -> np.ndarray:
    stamps = 1403636579763555584 + np.arange(n, dtype=np.int64) * 50_000_000
    names = [f"{s}.png" for s in stamps]
    for i, name in enumerate(names):
        save_png(root / "mav0/cam0/data" / name, 10 * i)
    if corrupt is not None:
        (root / "mav0/cam0/data" / names[corrupt]).write_bytes(b"garbage")
    write_euroc_image_list(root / "mav0/cam0/data.csv", stamps, names)
    return stamps


SENSOR_YAML = """\
T_BS:
  cols: 4
  rows: 4
  data: [0.0, -1.0, 0.0, 0.1,
         1.0, 0.0, 0.0, 0.2,
         0.0, 0.0, 1.0, 0.3,
         0.0, 0.0, 0.0, 1.0]
resolution: [8, 6]
camera_model: pinhole
intrinsics: [4.0, 4.5, 3.5, 2.5]
distortion_model: radial-tangential
distortion_coefficients: [0.0, 0.0, 0.0, 0.0]
"""


def test_open_euroc(tmp_path: Path) -> None:
    root = tmp_path / "MH_01"
    stamps = make_euroc(root, corrupt=2)
    write(root / "mav0/cam0/sensor.yaml", SENSOR_YAML)
    body = random_trajectory(20, seed=1, t0=1403636579.5)
    write_euroc_groundtruth(root / "mav0/state_groundtruth_estimate0/data.csv", body)
    ds = open_dataset(root)
    assert (ds.name, ds.format, len(ds)) == ("MH_01", "euroc", 5)
    assert np.allclose(ds.timestamps, stamps * 1e-9, atol=1e-6)
    assert np.array_equal(ds.timestamps_ns, stamps)
    assert ds.image_path(1) == root / f"mav0/cam0/data/{stamps[1]}.png"
    frames = list(ds.frames())
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    assert frames[2].image is None and "cannot decode" in frames[2].error
    assert frames[3].image is not None and frames[3].image[0, 0] == 30 and frames[3].error is None
    cal = ds.calibration
    assert cal.camera_type == "pinhole" and (cal.width, cal.height) == (8, 6)
    assert cal.intrinsics == {"fx": 4.0, "fy": 4.5, "cx": 3.5, "cy": 2.5}
    T_BS = np.array([[0, -1, 0, 0.1], [1, 0, 0, 0.2], [0, 0, 1, 0.3], [0, 0, 0, 1.0]])
    assert np.allclose(ds.ground_truth.poses, body.poses @ T_BS, atol=1e-12)
    assert open_dataset(root / "mav0").format == "euroc"  # the mav0 folder itself


def test_open_euroc_distortion_and_calib_override(tmp_path: Path) -> None:
    root = tmp_path / "seq"
    make_euroc(root)
    write(root / "mav0/cam0/sensor.yaml", EUROC_SENSOR_YAML)
    ds = open_dataset(root)  # EuRoC's own radial-tangential camera: undistorted to a pinhole
    assert ds.calibration.camera_type == "pinhole" and "radial-tangential" in ds.notes[0]
    assert ds.undistortion.source.intrinsics["k1"] == -0.28340811
    assert np.allclose(ds.calibration.T_imu_cam, ds.undistortion.source.T_imu_cam)
    assert ds.ground_truth is None
    write(root / "mav0/cam0/sensor.yaml", EUROC_SENSOR_YAML.replace(
        "distortion_model: radial-tangential", "distortion_model: fov").replace(
        "[-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]", "[0.9]"))
    ds = open_dataset(root)
    assert ds.calibration is None and "'fov'" in ds.notes[0] and ds.undistortion is None
    write_calibration(tmp_path / "my.json", CALIBS[1])
    assert open_dataset(root, calib_path=tmp_path / "my.json").calibration.camera_type == "kb4"


def test_pinhole_sensor_yaml_with_three_intrinsics_says_so(tmp_path: Path, capsys) -> None:
    from granite.cli.main import main

    root = tmp_path / "seq"
    make_euroc(root)
    write(root / "mav0/cam0/sensor.yaml", SENSOR_YAML.replace("[4.0, 4.5, 3.5, 2.5]", "[4.0, 4.5, 3.5]"))
    ds = open_dataset(root)
    assert ds.calibration is None and "pinhole needs 4 intrinsics [fu, fv, cu, cv], got 3" in ds.notes[0]
    assert main(["run", str(root), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "needs 4 intrinsics [fu, fv, cu, cv], got 3" in err
    assert "unsupported camera_model" not in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_open_testbench_prefers_root_files(tmp_path: Path) -> None:
    root = tmp_path / "bench"
    make_euroc(root)
    write(root / "mav0/cam0/sensor.yaml", SENSOR_YAML)
    write_calibration(root / "calib.json", CALIBS[2])
    gt = random_trajectory(10, seed=2, t0=1403636579.0)
    write_tum(root / "groundtruth.tum", gt)
    other = random_trajectory(10, seed=9)
    write_euroc_groundtruth(root / "mav0/state_groundtruth_estimate0/data.csv", other)
    ds = open_dataset(root)
    assert ds.format == "testbench"
    assert ds.calibration.camera_type == "ds"
    assert np.allclose(ds.ground_truth.poses, gt.poses, atol=1e-12)
    write_calibration(tmp_path / "other.json", CALIBS[0])
    assert open_dataset(root, tmp_path / "other.json").calibration.camera_type == "pinhole"


def test_open_tum_rgbd(tmp_path: Path) -> None:
    root = tmp_path / "rgbd_dataset_freiburg1_xyz"
    lines = ["# color images", "# timestamp filename"]
    for i in range(4):
        save_png(root / f"rgb/{i}.png", i)
        lines.append(f"{1305031102.175304 + 0.033 * i:.6f} rgb/{i}.png")
    write(root / "rgb.txt", "\n".join(lines) + "\n")
    gt = random_trajectory(8, seed=4, t0=1305031102.0)
    write_tum(root / "groundtruth.txt", gt)
    ds = open_dataset(root)
    assert (ds.format, len(ds), ds.calibration) == ("tum", 4, None)
    assert "640x480" in ds.notes[0]  # the freiburg1 camera's, but these images are 8x6
    assert ds.timestamps[1] == pytest.approx(1305031102.208304)
    assert [int(f.image[0, 0]) for f in ds.frames()] == [0, 1, 2, 3]
    assert np.allclose(ds.ground_truth.poses, gt.poses, atol=1e-12)


@pytest.mark.parametrize("camera", ["freiburg1", "freiburg3", "kinect"])
def test_open_tum_rgbd_with_the_published_calibration(tmp_path: Path, camera: str) -> None:
    root = tmp_path / f"rgbd_dataset_{camera}_desk"
    (root / "rgb").mkdir(parents=True)
    cv2.imwrite(str(root / "rgb/0.png"), np.full((480, 640, 3), 90, np.uint8))
    write(root / "rgb.txt", "1305031102.175304 rgb/0.png\n")
    ds = open_dataset(root)
    if camera == "kinect":
        assert ds.calibration is None and "freiburg1/2/3" in ds.notes[0]
        return
    assert (ds.calibration.camera_type, ds.calibration.width, ds.calibration.height) == ("pinhole", 640, 480)
    if camera == "freiburg1":  # radial-tangential: undistorted on read
        assert ds.undistortion.source.intrinsics["fx"] == 517.306408
        assert ds.undistortion.source.intrinsics["k3"] == 1.163314
    else:
        assert ds.undistortion is None and ds.calibration.intrinsics["fy"] == 539.2
    write_calibration(root / "calib.json", CALIBS[0])  # a calib.json wins
    assert open_dataset(root).calibration.intrinsics == CALIBS[0].intrinsics


def test_open_kitti_colour_camera(tmp_path: Path) -> None:
    """The colour download (image_2 only): camera 2's intrinsics, and camera 0's ground truth
    moved to camera 2, whose projection ``P2 = K [I | t]`` places it at ``-t`` in camera 0's
    frame (built here from a chosen K and t)."""
    seq = tmp_path / "dataset/sequences/00"
    (seq / "image_2").mkdir(parents=True)
    for i in range(2):
        assert cv2.imwrite(str(seq / f"image_2/{i:06d}.png"), np.full((6, 8, 3), 50 + i, np.uint8))
    write(seq / "times.txt", "0.0\n0.1\n")
    K = np.array([[700.0, 0, 600], [0, 700, 180], [0, 0, 1]])
    t = np.array([0.06, -0.0003, 0.002])
    P2 = np.hstack([K, (K @ t)[:, None]])
    write(seq / "calib.txt", "P0: 7.07e+02 0 6.01e+02 0 0 7.08e+02 1.83e+02 0 0 0 1 0\n"
          + "P2: " + " ".join(repr(float(v)) for v in P2.ravel()) + "\n")
    write(tmp_path / "dataset/poses/00.txt",
          "1 0 0 0 0 1 0 0 0 0 1 0\n0 -1 0 1 1 0 0 2 0 0 1 3\n")
    ds = open_dataset(seq)
    assert ds.calibration.intrinsics == {"fx": 700.0, "fy": 700.0, "cx": 600.0, "cy": 180.0}
    assert ds.frame(1).image[0, 0] == 51 and "camera 2" in ds.notes[0]
    # x_2 = K (X_0 + t): camera 2's centre is at -t in camera 0's frame
    expected_1 = np.array([[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1.0]])
    expected_1[:3, 3] += expected_1[:3, :3] @ -t
    assert np.allclose(ds.ground_truth.poses[1], expected_1, atol=1e-12)
    assert np.allclose(ds.ground_truth.poses[0][:3, 3], -t, atol=1e-12)


def test_open_kitti(tmp_path: Path) -> None:
    seq = tmp_path / "dataset/sequences/05"
    for i in range(3):
        save_png(seq / f"image_0/{i:06d}.png", 100 + i)
    write(seq / "times.txt", "0.000000e+00\n1.036000e-01\n2.072000e-01\n")
    write(seq / "calib.txt",
          "P0: 7.07e+02 0 6.01e+02 0 0 7.08e+02 1.83e+02 0 0 0 1 0\nP1: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    write(tmp_path / "dataset/poses/05.txt",
          "1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0.5 0 1 0 0 0 0 1 1.0\n0 -1 0 1 1 0 0 2 0 0 1 3\n")
    ds = open_dataset(seq)
    assert (ds.name, ds.format, len(ds)) == ("05", "kitti", 3)
    assert np.allclose(ds.timestamps, [0.0, 0.1036, 0.2072])
    cal = ds.calibration
    assert cal.intrinsics == {"fx": 707.0, "fy": 708.0, "cx": 601.0, "cy": 183.0}
    assert (cal.width, cal.height) == (8, 6)
    gt = ds.ground_truth
    assert np.array_equal(gt.positions[2], [1, 2, 3])
    assert np.allclose(gt.poses[2, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    assert ds.frame(2).image[0, 0] == 102


def test_open_dataset_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="dataset folder not found"):
        open_dataset(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="unknown dataset layout"):
        open_dataset(tmp_path / "empty")
    e = tmp_path / "e"
    write(e / "mav0/cam0/data.csv", "#timestamp [ns],filename\n")
    with pytest.raises(InputError, match="no images listed") as info:
        open_dataset(e)
    assert info.value.path == e / "mav0/cam0/data.csv"
    u = tmp_path / "u"
    csv = write(u / "mav0/cam0/data.csv", "#timestamp [ns],filename\n20,a.png\n10,b.png\n")
    with pytest.raises(InputError, match="unsorted") as info:
        open_dataset(u)
    assert (info.value.path, info.value.line) == (csv, 3)
    m = tmp_path / "m"
    csv = write(m / "mav0/cam0/data.csv", "#timestamp [ns],filename\n20,a.png,3\n")
    with pytest.raises(InputError, match="2 columns") as info:
        open_dataset(m)
    assert (info.value.path, info.value.line) == (csv, 2)
    k = tmp_path / "k"
    save_png(k / "image_0/000000.png", 1)
    write(k / "times.txt", "0.0\n0.1\n")
    with pytest.raises(InputError, match="2 timestamps but 1 images"):
        open_dataset(k)
    r = tmp_path / "r"
    write(r / "rgb.txt", "1.0 rgb/a.png\n1.0 rgb/b.png\n")
    with pytest.raises(InputError, match="duplicate") as info:
        open_dataset(r)
    assert info.value.line == 2


def test_missing_image_yields_none(tmp_path: Path) -> None:
    root = tmp_path / "seq"
    stamps = make_euroc(root, n=3)
    (root / f"mav0/cam0/data/{stamps[1]}.png").unlink()
    frames = list(open_dataset(root).frames())
    assert frames[1].image is None and "not found" in frames[1].error
    assert frames[0].image is not None and frames[2].image is not None
