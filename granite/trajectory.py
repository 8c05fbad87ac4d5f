"""The one trajectory type shared by io, evaluation and the VO.

A :class:`Trajectory` holds ``N`` camera poses ``T_w_c`` (4x4 float64, camera-to-world,
``p_w = T_w_c @ p_c``) at strictly increasing timestamps in seconds, and optionally the
integer sub-map index of every pose. A monocular VO starts a new sub-map (with a new,
unrelated scale and origin) after every tracking failure; poses of different sub-maps must
never be compared directly.

Sub-map *runs* are maximal blocks of consecutive poses with the same index; a run is one
continuously tracked section.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Tolerance on ``R^T R - I`` and on the last row of a pose.
_ORTHONORMAL_TOL = 1e-5


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Timestamped camera poses ``T_w_c``.

    Attributes:
        timestamps: ``(N,)`` float64 seconds, finite and strictly increasing.
        poses: ``(N, 4, 4)`` float64 ``T_w_c``; rotation blocks orthonormal with det +1.
        submap: ``(N,)`` int64 sub-map index per pose, or ``None`` (one sub-map).

    Arrays are copied and made read-only. Invalid input raises :class:`ValueError` (the io
    readers turn bad files into :class:`granite.errors.InputError` before this point).
    """

    timestamps: np.ndarray
    poses: np.ndarray
    submap: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = np.array(self.timestamps, dtype=np.float64, copy=True)
        poses = np.array(self.poses, dtype=np.float64, copy=True)
        if t.ndim != 1:
            raise ValueError(f"timestamps must be 1-D, got shape {t.shape}")
        n = t.shape[0]
        if poses.shape != (n, 4, 4):
            raise ValueError(f"poses must have shape ({n}, 4, 4), got {poses.shape}")
        if not np.all(np.isfinite(t)):
            raise ValueError("timestamps must be finite")
        if n > 1 and not np.all(np.diff(t) > 0):
            i = int(np.argmin(np.diff(t) > 0)) + 1
            raise ValueError(
                f"timestamps must be strictly increasing (index {i}: {t[i - 1]!r} -> {t[i]!r})"
            )
        if not np.all(np.isfinite(poses)):
            raise ValueError("poses must be finite")
        if n:
            bottom = poses[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])
            if np.max(np.abs(bottom)) > _ORTHONORMAL_TOL:
                raise ValueError("the last row of every pose must be [0, 0, 0, 1]")
            R = poses[:, :3, :3]
            err = np.einsum("nji,njk->nik", R, R) - np.eye(3)
            if np.max(np.abs(err)) > _ORTHONORMAL_TOL or np.any(np.linalg.det(R) <= 0):
                raise ValueError("pose rotations must be orthonormal with determinant +1")
        submap = self.submap
        if submap is not None:
            raw = np.asarray(submap)
            if raw.shape != (n,):
                raise ValueError(f"submap must have shape ({n},), got {raw.shape}")
            if raw.dtype.kind == "f":
                if not np.all(np.isfinite(raw)) or not np.all(raw == np.round(raw)):
                    raise ValueError("submap indices must be integers")
            elif raw.dtype.kind not in "iu":
                raise ValueError(f"submap indices must be integers, got dtype {raw.dtype}")
            submap = np.array(raw, dtype=np.int64, copy=True)
            submap.setflags(write=False)
        t.setflags(write=False)
        poses.setflags(write=False)
        object.__setattr__(self, "timestamps", t)
        object.__setattr__(self, "poses", poses)
        object.__setattr__(self, "submap", submap)

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    @property
    def positions(self) -> np.ndarray:
        """``(N, 3)`` camera centres in the world frame."""
        return self.poses[:, :3, 3]

    @property
    def rotations(self) -> np.ndarray:
        """``(N, 3, 3)`` rotations ``R_w_c``."""
        return self.poses[:, :3, :3]

    @property
    def duration(self) -> float:
        """Last minus first timestamp (0 for fewer than two poses)."""
        return float(self.timestamps[-1] - self.timestamps[0]) if len(self) > 1 else 0.0

    def submap_ids(self) -> np.ndarray:
        """``(N,)`` int64 sub-map index per pose (all zeros when :attr:`submap` is ``None``)."""
        if self.submap is None:
            return np.zeros(len(self), dtype=np.int64)
        return self.submap

    def runs(self) -> list[tuple[int, int]]:
        """Index ranges ``[start, stop)`` of maximal blocks with the same sub-map index."""
        n = len(self)
        if n == 0:
            return []
        ids = self.submap_ids()
        cuts = np.flatnonzero(np.diff(ids) != 0) + 1
        bounds = [0, *cuts.tolist(), n]
        return [(bounds[k], bounds[k + 1]) for k in range(len(bounds) - 1)]

    def path_length(self) -> float:
        """Sum of distances between consecutive positions within each sub-map run.

        Jumps between sub-maps are not counted (they compare unrelated frames).
        """
        total = 0.0
        p = self.positions
        for a, b in self.runs():
            if b - a > 1:
                total += float(np.sum(np.linalg.norm(np.diff(p[a:b], axis=0), axis=1)))
        return total

    def select(self, indices: np.ndarray | slice) -> Trajectory:
        """A new trajectory with the poses at ``indices`` (an index array, boolean mask or
        slice; order must keep timestamps increasing)."""
        sub = None if self.submap is None else self.submap[indices]
        return Trajectory(self.timestamps[indices], self.poses[indices], sub)

    def with_poses(self, poses: np.ndarray) -> Trajectory:
        """The same timestamps and sub-maps with other poses."""
        return Trajectory(self.timestamps, poses, self.submap)
