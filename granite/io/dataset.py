"""Image sequence datasets with optional ground truth and calibration.

:func:`open_dataset` detects the layout of a folder:

* ``euroc``: EuRoC/ASL, ``<root>/mav0/cam0/data.csv`` + ``data/`` (also accepted when the
  path is the ``mav0`` folder itself). Calibration from ``cam0/sensor.yaml`` (pinhole with
  radial-tangential distortion, or equidistant = ``kb4``); ground truth from
  ``mav0/state_groundtruth_estimate0/data.csv`` converted to camera poses with ``T_BS``.
* ``testbench``: the granite test-bench output, EuRoC layout plus ``calib.json`` and/or
  ``groundtruth.tum`` (camera poses ``T_w_c``) at the root; these are preferred.
* ``tum``: TUM RGB-D, ``rgb.txt`` (+ optional ``groundtruth.txt``); without a ``calib.json``,
  the published calibration of the freiburg1/2/3 camera named in the folder name.
* ``kitti``: KITTI odometry sequence, ``image_0/`` (else ``image_1..3/``, e.g. the colour
  download) + ``times.txt`` (+ ``calib.txt``; ground truth ``../../poses/<name>.txt``, camera
  0's poses, moved to the camera used by ``calib.txt``).

In every layout a ``calib.json`` (Basalt format) at the root is preferred, and an explicit
``calib_path`` / ``groundtruth_path`` overrides everything. A radial-tangential calibration
(``pinhole-radtan8``; EuRoC's distortion) makes the dataset undistort every image it reads to a
pinhole camera, which is then its ``calibration`` (:mod:`granite.io.undistortion`; ``notes``
says so). Layout problems raise
:class:`InputError` when the dataset is opened; unreadable images do not: :meth:`Dataset.frames`
yields them with ``image=None`` and the reason, for the VO to skip and count.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from granite.errors import InputError
from granite.io.calibration import RADTAN, Calibration, read_calibration
from granite.io.euroc import (
    read_euroc_groundtruth,
    read_euroc_image_list,
    read_sensor_yaml,
    seconds_from_ns,
)
from granite.io.images import read_image
from granite.io.kitti import read_kitti_poses, read_kitti_projection, read_kitti_times
from granite.io.trajectory_file import read_trajectory
from granite.io.tum import read_tum
from granite.io.tum_rgbd import read_tum_rgbd_list
from granite.io.undistortion import Undistortion
from granite.trajectory import Trajectory

FORMATS = ("euroc", "testbench", "tum", "kitti")


@dataclass(frozen=True, eq=False)
class Frame:
    """One image of a dataset; ``image`` is ``None`` when it could not be read, and ``error``
    then says why."""

    index: int
    timestamp: float
    image: np.ndarray | None
    error: str | None
    path: Path


class Dataset:
    """An opened image sequence (see :func:`open_dataset`).

    Attributes:
        name: folder name of the sequence.
        format: one of :data:`FORMATS`.
        root: the dataset folder.
        timestamps: ``(N,)`` float64 seconds, strictly increasing (read-only).
        timestamps_ns: ``(N,)`` int64 nanoseconds for EuRoC layouts, else ``None``.
        ground_truth: camera poses ``T_w_c`` or ``None``.
        calibration: :class:`Calibration` or ``None`` (``notes`` says why when it is missing);
            the camera of the images :meth:`frame` returns (never radial-tangential).
        undistortion: the :class:`~granite.io.undistortion.Undistortion` applied to every image
            read (its ``source`` is the radial-tangential calibration), or ``None``.
        notes: human-readable remarks made while opening (e.g. unsupported distortion).
    """

    def __init__(
        self,
        name: str,
        format: str,
        root: Path,
        timestamps: np.ndarray,
        image_paths: list[Path],
        ground_truth: Trajectory | None = None,
        calibration: Calibration | None = None,
        timestamps_ns: np.ndarray | None = None,
        notes: tuple[str, ...] = (),
    ):
        if len(image_paths) != len(timestamps):
            raise ValueError("one image path per timestamp required")
        self.name = name
        self.format = format
        self.root = root
        self.timestamps = np.array(timestamps, dtype=np.float64)
        self.timestamps.setflags(write=False)
        self.timestamps_ns = None if timestamps_ns is None else np.array(timestamps_ns, np.int64)
        self._image_paths = list(image_paths)
        self.ground_truth = ground_truth
        self.undistortion = None
        self.calibration = calibration
        self.notes = tuple(notes)
        if calibration is not None and calibration.camera_type == RADTAN:
            try:
                self.undistortion = Undistortion(calibration)
            except ValueError as error:
                raise InputError(f"radial-tangential calibration: {error}", root) from None
            self.calibration = self.undistortion.target
            self.notes += (self.undistortion.describe(),)

    def __len__(self) -> int:
        return len(self._image_paths)

    def __repr__(self) -> str:
        return (
            f"Dataset(name={self.name!r}, format={self.format!r}, frames={len(self)}, "
            f"ground_truth={self.ground_truth is not None}, "
            f"calibration={self.calibration is not None})"
        )

    def image_path(self, index: int) -> Path:
        """Path of image ``index`` (0-based; negative indices count from the end)."""
        return self._image_paths[index]

    def frame(self, index: int) -> Frame:
        """Load frame ``index``; an unreadable image gives ``image=None`` and the reason."""
        if index < 0:
            index += len(self)
        path = self._image_paths[index]
        t = float(self.timestamps[index])
        try:
            image = read_image(path)
        except InputError as error:
            return Frame(index, t, None, error.message, path)
        if self.undistortion is not None:
            image = self.undistortion.apply(image)
        return Frame(index, t, image, None, path)

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[Frame]:
        """Lazily yield frames ``start .. stop-1`` in time order (images read one at a time)."""
        stop = len(self) if stop is None else min(stop, len(self))
        for index in range(max(start, 0), stop):
            yield self.frame(index)


# --------------------------------------------------------------------------- layouts


#: ``distortion_model`` names of the radial-tangential model in ``sensor.yaml`` files.
_RADTAN_NAMES = ("radial-tangential", "radtan", "plumb_bob", "rational_polynomial")


def _calibration_from_sensor(path: Path, notes: list[str]) -> Calibration | None:
    if not path.is_file():
        notes.append(f"no calibration: {path} not found")
        return None
    info = read_sensor_yaml(path)
    missing = [k for k in ("resolution", "intrinsics") if getattr(info, k) is None]
    if missing:
        notes.append(f"no calibration: {path} lacks {', '.join(missing)}")
        return None
    if info.camera_model not in (None, "pinhole"):
        notes.append(f"no calibration: unsupported camera_model {info.camera_model!r} in {path}")
        return None
    if len(info.intrinsics) != 4:
        notes.append(f"no calibration: camera_model pinhole needs 4 intrinsics [fu, fv, cu, cv], got "
                     f"{len(info.intrinsics)} in {path}")
        return None
    fx, fy, cx, cy = info.intrinsics
    params = {"fx": fx, "fy": fy, "cx": cx, "cy": cy}
    dist = info.distortion_coefficients
    model = info.distortion_model
    T = np.eye(4) if info.T_BS is None else info.T_BS
    w, h = info.resolution
    if model == "equidistant" and len(dist) == 4:
        params.update(zip(("k1", "k2", "k3", "k4"), dist))
        return Calibration("kb4", params, w, h, T)
    if not any(dist):
        return Calibration("pinhole", params, w, h, T)
    if model in _RADTAN_NAMES and len(dist) in (4, 5, 8):
        # OpenCV's order: k1 k2 p1 p2 [k3 [k4 k5 k6]]
        params.update(zip(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"), dist))
        return Calibration(RADTAN, params, w, h, T)
    notes.append(
        f"no calibration: distortion model {model!r} with {len(dist)} coefficients of {path} is "
        "not supported (radial-tangential takes 4, 5 or 8; or use pinhole, kb4 or ds in a calib.json)"
    )
    return None


def _open_euroc(root: Path, mav0: Path, calib: Calibration | None, gt_path: Path | None) -> Dataset:
    notes: list[str] = []
    cam0 = mav0 / "cam0"
    stamps_ns, names = read_euroc_image_list(cam0 / "data.csv")
    if calib is None:
        calib = _calibration_from_sensor(cam0 / "sensor.yaml", notes)
    testbench = (root / "calib.json").is_file() or (root / "groundtruth.tum").is_file()
    T_body_cam = None if calib is None else calib.T_imu_cam
    gt = None
    euroc_gt = mav0 / "state_groundtruth_estimate0" / "data.csv"
    if gt_path is not None:
        gt = read_trajectory(gt_path, T_body_cam)
    elif (root / "groundtruth.tum").is_file():
        gt = read_tum(root / "groundtruth.tum")
    elif euroc_gt.is_file():
        gt = read_euroc_groundtruth(euroc_gt, T_body_cam)
    return Dataset(
        name=root.name,
        format="testbench" if testbench else "euroc",
        root=root,
        timestamps=seconds_from_ns(stamps_ns),
        image_paths=[cam0 / "data" / n for n in names],
        ground_truth=gt,
        calibration=calib,
        timestamps_ns=stamps_ns,
        notes=tuple(notes),
    )


#: The published intrinsics of the three TUM RGB-D cameras (the dataset's "file formats"
#: page; the ROS default calibration for freiburg3, whose images are undistorted): fx fy cx cy
#: and the radial-tangential k1 k2 p1 p2 k3 of the 640x480 colour images.
TUM_RGBD_CAMERAS = {
    "freiburg1": (517.306408, 516.469215, 318.643040, 255.313989,
                  0.262383, -0.953104, -0.005358, 0.002628, 1.163314),
    "freiburg2": (520.908620, 521.007327, 325.141442, 249.701764,
                  0.231222, -0.784899, -0.003257, -0.000105, 0.917205),
    "freiburg3": (535.4, 539.2, 320.1, 247.6, 0.0, 0.0, 0.0, 0.0, 0.0),
}


def _tum_rgbd_camera(root: Path, images: list[Path], notes: list[str]) -> Calibration | None:
    """The published calibration of the TUM RGB-D camera named in the folder name
    (``rgbd_dataset_freiburg1_xyz``), for its 640x480 images."""
    camera = next((c for c in TUM_RGBD_CAMERAS if c in root.name), None)
    if camera is None:
        notes.append(f"no calibration: no calib.json in {root} (and no freiburg1/2/3 in its name)")
        return None
    size = _first_image_size(images)
    if size != (640, 480):
        notes.append(f"no calibration: the {camera} camera's images are 640x480, these {size}")
        return None
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = TUM_RGBD_CAMERAS[camera]
    notes.append(f"calibration: the published intrinsics of the TUM RGB-D {camera} camera "
                 "(a calib.json in the folder or --calib overrides them)")
    params = {"fx": fx, "fy": fy, "cx": cx, "cy": cy}
    if not any((k1, k2, p1, p2, k3)):
        return Calibration("pinhole", params, 640, 480)
    return Calibration(RADTAN, {**params, "k1": k1, "k2": k2, "p1": p1, "p2": p2, "k3": k3}, 640, 480)


def _open_tum(root: Path, calib: Calibration | None, gt_path: Path | None) -> Dataset:
    times, names = read_tum_rgbd_list(root / "rgb.txt")
    notes: list[str] = []
    if calib is None:
        calib = _tum_rgbd_camera(root, [root / n for n in names], notes)
    gt_default = root / "groundtruth.txt"
    gt = None
    if gt_path is not None:
        gt = read_trajectory(gt_path)
    elif gt_default.is_file():
        gt = read_tum(gt_default)
    return Dataset(root.name, "tum", root, times, [root / n for n in names], gt, calib,
                   notes=tuple(notes))


#: KITTI odometry image folders in order of preference: the left grayscale camera, the right
#: one, then the colour cameras (the colour download holds only those).
KITTI_IMAGE_DIRS = ("image_0", "image_1", "image_2", "image_3")


def _open_kitti(root: Path, calib: Calibration | None, gt_path: Path | None) -> Dataset:
    times_path = root / "times.txt"
    found = [d for d in KITTI_IMAGE_DIRS if (root / d).is_dir()]
    if not found:
        raise InputError(f"KITTI layout: none of {', '.join(KITTI_IMAGE_DIRS)} found", root)
    image_dir = root / found[0]
    camera = int(found[0][-1])
    times = read_kitti_times(times_path)
    images = sorted(image_dir.glob("*.png"))
    if not images:
        raise InputError("no .png images", image_dir)
    if len(images) != len(times):
        message = f"{len(times)} timestamps but {len(images)} images in {image_dir}"
        raise InputError(message, times_path)
    notes: list[str] = []
    calib_txt = root / "calib.txt"
    T_c0_ci = np.eye(4)
    if calib_txt.is_file():
        params, T_c0_ci = read_kitti_projection(calib_txt, camera)
        if calib is None:
            size = _first_image_size(images)
            if size is None:
                notes.append(f"no calibration: no image in {image_dir} could be read")
            else:
                calib = Calibration("pinhole", params, size[0], size[1])
    elif calib is None:
        notes.append(f"no calibration: {calib_txt} not found")
    if camera != 0:
        notes.append(f"images of camera {camera} ({image_dir.name}); its ground truth is camera 0's "
                     f"moved by {T_c0_ci[:3, 3].round(4).tolist()} m" if calib_txt.is_file()
                     else f"images of camera {camera}; without calib.txt its ground truth is camera 0's")
    gt = None
    gt_default = root.parent.parent / "poses" / f"{root.name}.txt"
    if gt_path is not None:
        gt = read_kitti_poses(gt_path, times)
    elif gt_default.is_file():
        gt = read_kitti_poses(gt_default, times)
    if gt is not None and camera != 0:  # the poses files hold camera 0's poses
        gt = Trajectory(gt.timestamps, gt.poses @ T_c0_ci, gt.submap)
    return Dataset(root.name, "kitti", root, times, images, gt, calib, notes=tuple(notes))


def _first_image_size(paths: list[Path]) -> tuple[int, int] | None:
    for path in paths:
        try:
            image = read_image(path)
        except InputError:
            continue
        return image.shape[1], image.shape[0]
    return None


def open_dataset(
    path: str | Path,
    calib_path: str | Path | None = None,
    groundtruth_path: str | Path | None = None,
) -> Dataset:
    """Open the dataset folder ``path``, detecting its layout (see the module docstring).

    ``calib_path`` (Basalt JSON) overrides the dataset's calibration; ``groundtruth_path``
    overrides its ground truth (TUM or EuRoC CSV; a KITTI poses file for KITTI).
    """
    root = Path(path)
    if not root.exists():
        raise InputError("dataset folder not found", root)
    if not root.is_dir():
        raise InputError("dataset path is not a folder", root)
    calib = None
    if calib_path is not None:
        calib = read_calibration(calib_path)
    elif (root / "calib.json").is_file():
        calib = read_calibration(root / "calib.json")
    gt_path = None if groundtruth_path is None else Path(groundtruth_path)
    if (root / "mav0" / "cam0").is_dir():
        return _open_euroc(root, root / "mav0", calib, gt_path)
    if root.name == "mav0" and (root / "cam0").is_dir():
        if calib is None and (root.parent / "calib.json").is_file():
            calib = read_calibration(root.parent / "calib.json")
        return _open_euroc(root.parent, root, calib, gt_path)
    if (root / "rgb.txt").is_file():
        return _open_tum(root, calib, gt_path)
    if any((root / d).is_dir() for d in KITTI_IMAGE_DIRS) or (root / "times.txt").is_file():
        if not (root / "times.txt").is_file():
            raise InputError("KITTI layout: times.txt not found", root / "times.txt")
        return _open_kitti(root, calib, gt_path)
    raise InputError(
        "unknown dataset layout: expected mav0/cam0/ (EuRoC/ASL or test-bench), rgb.txt "
        "(TUM RGB-D) or image_0/ (or image_1..3/) + times.txt (KITTI)",
        root,
    )
