"""Work sharing of the tracker's per-point passes (granite.optical_flow.work_share): every point
is claimed exactly once whoever joins, and the tracks are bit-identical to one thread's."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from numba import njit

from granite.optical_flow import FrameToFrameOpticalFlow, OpticalFlowConfig
from granite.optical_flow.synthetic import similarity, textured_image, warp
from granite.optical_flow.work_share import PointShare, fetch_add


@njit(nogil=True)
def _claim_all(counter, claimed_by, who, n, chunk):
    """Claim chunks until none is left; mark each claimed index with ``who`` (adds, so an
    index claimed twice ends above 2)."""
    while True:
        k0 = fetch_add(counter, 0, chunk)
        if k0 >= n:
            return
        for k in range(k0, min(k0 + chunk, n)):
            claimed_by[k] += who
            s = 0.0
            for j in range(2000):  # some work, so that both threads get chunks
                s += np.sin(j * 1e-3)
            if s < -1e300:
                claimed_by[k] = -1


def test_two_threads_claim_every_chunk_exactly_once():
    n, chunk = 20011, 7
    share = PointShare()
    claimed_by = np.zeros(n, dtype=np.int64)
    helper = threading.Thread(target=lambda: share.help())
    helper.start()  # waits for the share to open, then joins
    share.run(lambda: _claim_all(share.counter, claimed_by, 1, n, chunk))
    helper.join()
    assert np.all(claimed_by == 1)  # no index skipped, none claimed twice
    assert share.counter[0] >= n


def test_two_threads_both_work_on_an_open_share():
    n, chunk = 20011, 7
    share = PointShare()
    claimed_by = np.zeros(n, dtype=np.int64)
    work = {"owner": 1, "helper": 2}
    helper = threading.Thread(target=share.help)
    helper.start()
    share.run(lambda: _claim_all(share.counter, claimed_by,
                                 work[threading.current_thread().name == "MainThread" and "owner" or "helper"],
                                 n, chunk))
    helper.join()
    assert set(np.unique(claimed_by).tolist()) == {1, 2}  # each index once, by one of the two


def test_help_after_close_returns_and_an_error_of_a_helper_reaches_the_owner():
    share = PointShare()
    share.close()
    share.help()  # returns at once: nothing to join
    with pytest.raises(RuntimeError):
        share.run(lambda: None)

    failing = PointShare()

    def work():
        if threading.current_thread().name == "failing-helper":
            raise ValueError("helper failed")
        helper.join(5.0)  # the owner's work ends after the helper has failed

    helper = threading.Thread(target=failing.help, name="failing-helper")
    helper.start()
    with pytest.raises(ValueError, match="helper failed"):
        failing.run(work)


def test_shared_tracking_is_bit_identical_to_one_thread():
    """The frontend tracks a rotated, shifted image; a job with a shared point range, joined
    by two extra threads while it runs, gives the same tracks and ids as the plain job."""
    a = textured_image(480, 640, seed=3)
    b = warp(a, similarity(2.5, -1.5, 0.02, 1.0, (320.0, 240.0)))
    c = warp(a, similarity(4.0, -2.0, 0.03, 1.0, (320.0, 240.0)))

    def run(shared: bool):
        flow = FrameToFrameOpticalFlow(OpticalFlowConfig(), (640, 480))
        out = [flow.process(0.0, a)]
        for t, image in ((0.05, b), (0.1, c)):
            job = flow.begin(t, image, share_points=shared)
            helpers = [threading.Thread(target=job.wait) for _ in range(2)] if shared else []
            for h in helpers:
                h.start()
            job.run()
            for h in helpers:
                h.join()
            out.append(flow.complete(job))
        return out

    plain, shared = run(False), run(True)
    assert len(plain[1]) > 100  # enough points for many chunks
    for x, y in zip(plain, shared):
        assert np.array_equal(x.ids, y.ids)
        assert np.array_equal(x.positions, y.positions)
        assert np.array_equal(x.angles, y.angles)
        assert np.array_equal(x.levels, y.levels)
