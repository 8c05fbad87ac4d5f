"""Flat storage of observations ("slots") behind :class:`granite.backend.LandmarkDatabase`.

A slot holds one observation: landmark id, frame id, pixel ``uv`` (2,), pyramid level and an
alive flag, in growable numpy arrays in insertion order, so that packing a problem is a few
vectorised gathers. New observations are first appended to Python lists ("pending") and moved
into the arrays in bulk when the arrays are needed. Removed slots are marked dead and
compacted away (order preserving) on request; the caller renumbers its index with the map
:meth:`ObservationSlots.compact` returns. Slot numbers are stable until then.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Observation:
    """A landmark seen in a frame at pixel ``uv`` (2,), tracked from pyramid level ``level``."""

    uv: np.ndarray
    level: int


class ObservationSlots:
    """Growable slot arrays plus a pending list; see the module docstring."""

    def __init__(self, capacity: int = 1024) -> None:
        self._lm = np.empty(capacity, dtype=np.int64)
        self._frame = np.empty(capacity, dtype=np.int64)
        self._uv = np.empty((capacity, 2))
        self._level = np.empty(capacity, dtype=np.int64)
        self._alive = np.zeros(capacity, dtype=bool)
        self._n_flushed = 0  # slots [0, _n_flushed) are in the arrays
        self._p_lm: list[int] = []  # pending slots [_n_flushed, _n_flushed + len(_p_lm))
        self._p_frame: list[int] = []
        self._p_u: list[float] = []
        self._p_v: list[float] = []
        self._p_level: list[int] = []
        self._n_alive = 0

    @property
    def num_alive(self) -> int:
        return self._n_alive

    @property
    def num_dead(self) -> int:
        """Dead slots in the arrays (call after :meth:`flush`)."""
        return self._n_flushed - self._n_alive

    @property
    def next_slot(self) -> int:
        """The slot number the next appended observation gets."""
        return self._n_flushed + len(self._p_lm)

    def append(self, landmark_id: int, frame_id: int, u: float, v: float, level: int) -> int:
        """Append one observation (pending); returns its slot."""
        slot = self.next_slot
        self._p_lm.append(landmark_id)
        self._p_frame.append(frame_id)
        self._p_u.append(u)
        self._p_v.append(v)
        self._p_level.append(level)
        self._n_alive += 1
        return slot

    def extend(self, landmark_ids: np.ndarray, frame_id: int, uvs: np.ndarray,
               levels: np.ndarray) -> int:
        """Append observations made in one frame directly to the arrays (flushes first);
        returns the slot of the first one."""
        self.flush()
        base = self._n_flushed
        end = base + landmark_ids.shape[0]
        self._reserve(end)
        self._lm[base:end] = landmark_ids
        self._frame[base:end] = frame_id
        self._uv[base:end] = uvs
        self._level[base:end] = levels
        self._alive[base:end] = True
        self._n_flushed = end
        self._n_alive += end - base
        return base

    def set(self, slot: int, u: float, v: float, level: int) -> None:
        """Replace the pixel and level of a slot."""
        if slot >= self._n_flushed:
            i = slot - self._n_flushed
            self._p_u[i] = u
            self._p_v[i] = v
            self._p_level[i] = level
        else:
            self._uv[slot, 0] = u
            self._uv[slot, 1] = v
            self._level[slot] = level

    def set_flushed(self, slot: int, uv: np.ndarray, level) -> None:
        """Replace the pixel (2,) and level of a slot that is in the arrays."""
        self._uv[slot] = uv
        self._level[slot] = level

    def get(self, slot: int) -> Observation:
        if slot >= self._n_flushed:
            i = slot - self._n_flushed
            return Observation(np.array([self._p_u[i], self._p_v[i]]), self._p_level[i])
        return Observation(self._uv[slot].copy(), int(self._level[slot]))

    def kill(self, slot: int) -> None:
        if slot >= self._n_flushed:
            self.flush()
        self._alive[slot] = False
        self._n_alive -= 1

    def kill_many(self, slots: list[int]) -> None:
        self.flush()
        self._alive[slots] = False
        self._n_alive -= len(slots)

    def live_slots(self) -> np.ndarray:
        """Slot numbers of the live observations in the arrays (call after :meth:`flush`)."""
        return np.flatnonzero(self._alive[:self._n_flushed])

    def arrays(self) -> tuple[np.ndarray, ...]:
        """Views ``(alive, landmark ids, frame ids, uv, levels)`` of the slots in the arrays
        (call after :meth:`flush`; valid until the next change)."""
        n = self._n_flushed
        return self._alive[:n], self._lm[:n], self._frame[:n], self._uv[:n], self._level[:n]

    def landmark_ids(self, slots: np.ndarray) -> np.ndarray:
        return self._lm[slots]

    def frame_ids(self, slots: np.ndarray) -> np.ndarray:
        return self._frame[slots]

    def pixels(self, slots: np.ndarray) -> np.ndarray:
        return self._uv[slots]

    def levels(self, slots: np.ndarray) -> np.ndarray:
        return self._level[slots]

    def flush(self) -> None:
        """Move pending observations into the slot arrays."""
        k = len(self._p_lm)
        if k == 0:
            return
        n = self._n_flushed
        self._reserve(n + k)
        self._lm[n:n + k] = self._p_lm
        self._frame[n:n + k] = self._p_frame
        self._uv[n:n + k, 0] = self._p_u
        self._uv[n:n + k, 1] = self._p_v
        self._level[n:n + k] = self._p_level
        self._alive[n:n + k] = True
        self._n_flushed = n + k
        self._p_lm, self._p_frame, self._p_u, self._p_v, self._p_level = [], [], [], [], []

    def compact(self) -> list[int]:
        """Drop dead slots, keeping the order of the live ones (call after :meth:`flush`).
        Returns ``new_slot[old_slot]`` (-1 for dead slots)."""
        n = self._n_flushed
        keep = np.flatnonzero(self._alive[:n])
        m = keep.shape[0]
        remap = np.full(n, -1, dtype=np.int64)
        remap[keep] = np.arange(m, dtype=np.int64)
        for name in ("_lm", "_frame", "_uv", "_level"):
            arr = getattr(self, name)
            arr[:m] = arr[keep]
        self._alive[:m] = True
        self._alive[m:n] = False
        self._n_flushed = m
        return remap.tolist()

    def _reserve(self, size: int) -> None:
        cap = self._lm.shape[0]
        if size <= cap:
            return
        cap = max(2 * cap, size)
        n = self._n_flushed
        for name in ("_lm", "_frame", "_uv", "_level", "_alive"):
            old = getattr(self, name)
            new = np.zeros((cap,) + old.shape[1:], dtype=old.dtype)
            new[:n] = old[:n]
            setattr(self, name, new)
