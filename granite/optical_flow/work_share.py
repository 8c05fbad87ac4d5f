"""Dynamic sharing of a kernel's independent points among threads (bit-identical results).

A :class:`PointShare` hands out chunks of point indices ``[k0, k0 + chunk)`` through an atomic
counter that GIL-free numba kernels increment themselves (:func:`fetch_add`), so a thread that
would otherwise wait (the estimator's thread waiting for the next frame's tracks, or an idle
helper) can join the work while it runs, without a Python round trip per chunk. Every point
is processed exactly once, by whichever thread claims its chunk, from the same inputs: the
results do not depend on who joined or when.

Protocol: the owning thread :meth:`~PointShare.run` s the claiming kernel (which opens the
share to helpers), then runs the dependent work; any other thread may call
:meth:`~PointShare.help`, which runs the same kernel if the share is open and returns once no
chunk is left for it. :meth:`~PointShare.run` returns only after every helper that joined has
finished its chunk. :meth:`~PointShare.close` ends a share that was never opened.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic


@intrinsic
def fetch_add(typingctx, array, index, value):
    """``old = array[index]; array[index] += value; return old`` as one sequentially
    consistent atomic operation (1-D int64 arrays), for GIL-free numba kernels."""
    if not (isinstance(array, types.Array) and array.ndim == 1 and array.dtype == types.int64):
        return None
    sig = types.int64(array, types.intp, types.int64)

    def codegen(context, builder, signature, args):
        arr, idx, val = args
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, arr)
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [idx])
        return builder.atomic_rmw("add", ptr, val, "seq_cst")

    return sig, codegen


class PointShare:
    """The chunk counter of one kernel run and who works on it (see the module docstring).
    ``counter`` (1,) int64 is the next unclaimed point index, read and advanced by the kernel
    with :func:`fetch_add`."""

    def __init__(self) -> None:
        self.counter = np.zeros(1, dtype=np.int64)
        self._cond = threading.Condition()
        self._work: Callable[[], None] | None = None
        self._closed = False
        self._helpers = 0
        self._error: BaseException | None = None

    def run(self, work: Callable[[], None]) -> None:
        """Open the share with ``work`` (a call of the claiming kernel on ``counter``), run it
        on this thread, then close the share and wait for the helpers that joined. Re-raises
        a helper's error."""
        with self._cond:
            if self._closed:
                raise RuntimeError("a closed PointShare cannot run")
            self._work = work
            self._cond.notify_all()
        try:
            work()
        finally:
            with self._cond:
                self._closed = True
                while self._helpers:
                    self._cond.wait()
                self._work = None  # drop the kernel's arguments (it may refer to this share)
        if self._error is not None:
            raise self._error

    def help(self) -> None:
        """Join the work if the share is open (waits for it to open or close), until no chunk
        is left. Errors go to the owner (re-raised by :meth:`run`)."""
        with self._cond:
            while self._work is None and not self._closed:
                self._cond.wait()
            if self._closed:
                return
            work = self._work
            self._helpers += 1
        try:
            work()
        except BaseException as exc:  # noqa: BLE001 - handed to the owner
            self._error = exc
        finally:
            with self._cond:
                self._helpers -= 1
                self._cond.notify_all()

    def close(self) -> None:
        """End the share (idempotent): helpers waiting for it to open return."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
