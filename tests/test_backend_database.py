"""Landmark database storage: packing, batch insertion, caches (the fast paths of the window
must give exactly what the straightforward per-observation implementation gives)."""

from __future__ import annotations

import numpy as np
import pytest

from granite.backend import LandmarkDatabase, SlidingWindow
from granite.backend.reprojection import Workspace
from granite.backend.synthetic import build_window, default_camera, make_scene


def _reference_pack(db: LandmarkDatabase, frame_index, landmark_ids=None, target_filter=None):
    """The original per-observation packing loop (landmarks in id order, observations in the
    order they were added)."""
    ids = sorted(db.landmark_ids) if landmark_ids is None else list(landmark_ids)
    host, s, d, ptr, lm, tgt, uv, lvl = [], [], [], [0], [], [], [], []
    for i, lm_id in enumerate(ids):
        L = db.landmark(lm_id)
        host.append(frame_index[L.host_frame_id])
        s.append(np.array(L.s))
        d.append(L.inv_dist)
        n = 0
        for f, ob in db.observations(lm_id).items():
            if f not in frame_index or (target_filter is not None and f not in target_filter):
                continue
            lm.append(i)
            tgt.append(frame_index[f])
            uv.append(ob.uv)
            lvl.append(ob.level)
            n += 1
        ptr.append(ptr[-1] + n)
    return dict(landmark_ids=np.array(ids, dtype=np.int64), lm_host=np.array(host, dtype=np.int64),
                lm_s=np.array(s).reshape(-1, 2), lm_d=np.array(d, dtype=np.float64),
                lm_ptr=np.array(ptr, dtype=np.int64), obs_lm=np.array(lm, dtype=np.int64),
                obs_tgt=np.array(tgt, dtype=np.int64),
                obs_uv=np.array(uv, dtype=np.float64).reshape(-1, 2),
                obs_level=np.array(lvl, dtype=np.int64))


def _assert_pack_equal(db, frame_index, landmark_ids=None, target_filter=None):
    pk = db.pack(frame_index, landmark_ids, target_filter)
    ref = _reference_pack(db, frame_index, landmark_ids, target_filter)
    for name, value in ref.items():
        got = getattr(pk, name)
        assert got.dtype == value.dtype, name
        np.testing.assert_array_equal(got, value, err_msg=name)
    return pk


def test_pack_matches_reference_under_random_edits():
    rng = np.random.default_rng(3)
    db = LandmarkDatabase(compact_threshold=16)  # exercise compaction
    frames = list(range(10, 18))
    next_lm = 0
    for step in range(400):
        op = rng.integers(0, 10)
        if op < 2 or len(db) == 0:
            db.add_landmark(next_lm, int(rng.choice(frames)), rng.normal(size=3) + [0, 0, 3],
                            float(rng.uniform(0.0, 1.0)))
            next_lm += 1
        elif op < 6:
            lm = int(rng.choice(db.landmark_ids))
            f = int(rng.choice(frames))
            db.add_observation(lm, f, rng.uniform(0, 640, size=2), int(rng.integers(0, 3)))
        elif op == 6:
            lm = int(rng.choice(db.landmark_ids))
            obs = db.observations(lm)
            if obs:
                db.remove_observation(lm, int(rng.choice(list(obs))))
        elif op == 7 and len(db) > 5:
            db.remove_landmark(int(rng.choice(db.landmark_ids)))
        elif op == 8:
            lms = rng.choice(db.landmark_ids, size=min(len(db), 6), replace=False)
            db.add_observations(int(rng.choice(frames)), lms, rng.uniform(0, 640, (len(lms), 2)),
                                rng.integers(0, 3, len(lms)))
        else:
            db.set_inverse_distance(int(rng.choice(db.landmark_ids)), float(rng.uniform(0, 1)))
        if step % 20 == 0:
            index = {f: i for i, f in enumerate(frames)}
            pk = _assert_pack_equal(db, index)
            _assert_pack_equal(db, index)  # cached structure
            # states written back become row views; the next pack must see later edits
            pk.lm_s += 0.01
            pk.lm_d *= 0.5
            db.unpack_states(pk)
            _assert_pack_equal(db, index)
            if len(db):
                first = db.landmark(db.landmark_ids[0])
                first.s[0] += 0.1  # in place
                _assert_pack_equal(db, index)
                first.s = first.s + 0.2  # replaced
                _assert_pack_equal(db, index)
            subset = [i for i in db.landmark_ids if i % 3 == 0][::-1]
            _assert_pack_equal(db, index, subset, target_filter={10, 12, 13})
            assert db.num_observations == sum(len(db.observations(i)) for i in db.landmark_ids)
    # frames leave: observations and hosted landmarks go, the rest packs as before
    db.remove_frame(frames[0])
    _assert_pack_equal(db, {f: i for i, f in enumerate(frames[1:])})
    assert not db.observed_in(frames[0]) and not db.hosted_by(frames[0])


def test_copies_do_not_share_the_bearing_store():
    import copy
    import pickle

    scene = make_scene(num_frames=4, num_points=30, seed=6)
    win = build_window(scene)
    win.optimize(max_iterations=1)  # landmark bearings become row views of one store
    index = {f: i for i, f in enumerate(win.frame_ids)}
    for clone in (copy.deepcopy(win.landmarks), pickle.loads(pickle.dumps(win.landmarks))):
        first = clone.landmark(clone.landmark_ids[0])
        first.s[1] -= 0.05
        _assert_pack_equal(clone, index)
    _assert_pack_equal(win.landmarks, index)


def test_batch_observations_equal_sequential_ones():
    scene = make_scene(num_frames=5, num_points=60, seed=2)
    seq = build_window(scene)
    bat = SlidingWindow(seq.camera, seq.config)
    for f in seq.frame_ids:
        bat.add_frame(f, seq.pose(f), is_keyframe=seq.is_keyframe(f))
    for lm_id in seq.landmarks.landmark_ids:
        L = seq.landmarks.landmark(lm_id)
        bat.add_landmark(lm_id, L.host_frame_id, L.bearing, L.inv_dist)
    by_frame: dict[int, list] = {}
    for lm_id in sorted(seq.landmarks.landmark_ids):
        for f, ob in seq.landmarks.observations(lm_id).items():
            by_frame.setdefault(f, []).append((lm_id, ob.uv, ob.level))
    for f in seq.frame_ids:
        rows = by_frame.get(f, [])
        unknown = [(10_000 + k, np.zeros(2), 0) for k in range(3)]
        rows = unknown[:1] + rows + unknown[1:]
        n = bat.add_observations(f, [r[0] for r in rows], np.array([r[1] for r in rows]),
                                 [r[2] for r in rows], skip_unknown=True)
        assert n == len(rows) - 3
    index = {f: i for i, f in enumerate(seq.frame_ids)}
    a, b = seq.landmarks.pack(index), bat.landmarks.pack(index)
    for name in ("landmark_ids", "lm_host", "lm_ptr", "obs_lm", "obs_tgt", "obs_level"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    # same observations per landmark; order within a landmark follows insertion order
    for lm_id in seq.landmarks.landmark_ids:
        oa, ob = seq.landmarks.observations(lm_id), bat.landmarks.observations(lm_id)
        assert set(oa) == set(ob)
        for f in oa:
            np.testing.assert_array_equal(oa[f].uv, ob[f].uv)
            assert oa[f].level == ob[f].level
    assert seq.num_connected(seq.frame_ids[2]) == bat.num_connected(seq.frame_ids[2])


def test_batch_observations_validate_before_adding():
    win = SlidingWindow(default_camera())
    win.add_frame(1, np.eye(4), is_keyframe=True)
    win.add_frame(2, np.eye(4))
    for i in range(3):
        win.add_landmark(i, 1, np.array([0.1 * i, 0.0, 1.0]), 0.5)
    db = win.landmarks
    with pytest.raises(KeyError):
        win.add_observations(2, [0, 7], np.zeros((2, 2)))
    with pytest.raises(ValueError):
        win.add_observations(2, [0, 1], np.array([[1.0, 2.0], [np.nan, 0.0]]))
    with pytest.raises(ValueError):
        win.add_observations(2, [0, 1], np.zeros((3, 2)))
    with pytest.raises(KeyError):
        win.add_observations(3, [0], np.zeros((1, 2)))
    assert db.num_observations == 0 and not db.observed_in(2)
    # duplicates: the last one wins, as with sequential calls; replacing keeps one observation
    win.add_observations(2, [0, 1, 0], np.array([[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]]), [0, 1, 2])
    win.add_observation(1, 2, (5.0, 6.0), 2)
    assert db.num_observations == 2 and db.observed_in(2) == {0, 1}
    np.testing.assert_array_equal(db.observation(0, 2).uv, [3.0, 3.0])
    assert db.observation(0, 2).level == 2 and db.observation(1, 2).level == 2
    np.testing.assert_array_equal(db.observation(1, 2).uv, [5.0, 6.0])
    assert db.has_observation(0, 2) and not db.has_observation(2, 2)
    assert not db.has_observation(99, 2)
    with pytest.raises(ValueError):
        win.add_observation(2, 2, np.array([np.inf, 0.0]))
    with pytest.raises(ValueError):
        win.add_observation(2, 2, np.zeros(3))
    win.add_observation(2, 2, np.array([[7.0, 8.0]]))  # any shape with two elements
    np.testing.assert_array_equal(db.observations(2)[2].uv, [7.0, 8.0])


def test_num_connected_follows_inverse_distance_edits():
    scene = make_scene(num_frames=4, num_points=40, seed=4)
    win = build_window(scene)
    f = scene.frame_ids[2]
    seen = win.landmarks.observed_in(f)
    assert win.num_connected(f) == (len(seen), 0)
    for lm_id in list(seen)[:5]:
        win.set_inverse_distance(lm_id, 0.0)
    assert win.num_connected(f) == (len(seen) - 5, 5)
    assert win.num_connected(12345) == (0, 0)


def test_no_motion_pairs_match_reference():
    scene = make_scene(num_frames=6, num_points=80, seed=5)
    win = build_window(scene)
    db = win.landmarks
    for lm_id in db.landmark_ids[::2]:
        db.set_inverse_distance(lm_id, 0.0)
    problem = win.problem()
    pk = problem.packed
    k = len(problem.frame_ids)
    for _ in range(2):  # half, then all of the landmarks at d = 0
        host = pk.lm_host[pk.obs_lm]
        linked: dict[tuple[int, int], bool] = {}
        for o in range(pk.num_observations):
            h, t = int(host[o]), int(pk.obs_tgt[o])
            if h == t:
                continue
            key = (min(h, t), max(h, t))
            linked[key] = linked.get(key, False) or pk.lm_d[pk.obs_lm[o]] > 0.0
        expected = sorted((key for key, finite in linked.items() if not finite),
                          key=lambda p: p[0] * k + p[1])
        assert problem.no_motion_pairs(win.config.no_motion_weight) == expected
        pk.lm_d[:] = 0.0


def test_shared_workspace_views():
    ws = Workspace(10)
    v = ws.view(4)
    assert v.J_h.shape == (4, 2, 6) and v.J_h.flags.c_contiguous and v.w.shape == (4,)
    v.r[:] = 1.0
    assert np.all(ws.r[:4] == 1.0)
    with pytest.raises(ValueError):
        ws.view(11)


@pytest.mark.parametrize("id_base", [0, -5, 1 << 40])  # table lookups; negative / huge ids
def test_state_rows_compact_and_removed_landmarks_keep_their_state(id_base):
    """Landmark states live in rows of arrays: thousands of removals compact the rows, the
    landmark objects (views of the rows) follow, and packing still matches the reference."""
    rng = np.random.default_rng(7)
    db = LandmarkDatabase()
    frames = [1, 2, 3]
    index = {f: i for i, f in enumerate(frames)}
    alive: dict[int, tuple] = {}
    removed = []
    for k in range(3000):
        lm_id = id_base + k
        bearing = rng.normal(size=3) + [0, 0, 3]
        db.add_landmark(lm_id, int(rng.choice(frames)), bearing, float(rng.uniform(0, 1)))
        db.add_observation(lm_id, int(rng.choice(frames)), rng.uniform(0, 640, size=2), 0)
        L = db.landmark(lm_id)
        alive[lm_id] = (L.s.copy(), L.inv_dist)
        if k % 4:  # three of four leave again: the dead rows outnumber the live ones
            victim = int(rng.choice(list(alive)))
            obj = db.landmark(victim)
            db.remove_landmark(victim)
            removed.append((obj, alive.pop(victim)))
    assert len(db) == len(alive) and db._store.n < 3000  # compacted at least once
    for lm_id, (s, d) in alive.items():
        L = db.landmark(lm_id)
        np.testing.assert_array_equal(L.s, s)
        assert L.inv_dist == d
    for obj, (s, d) in removed[:50]:
        np.testing.assert_array_equal(obj.s, s)
        assert obj.inv_dist == d
    ids = sorted(alive)
    np.testing.assert_array_equal(db.inverse_distances(ids + [id_base - 1]),
                                  [alive[i][1] for i in ids] + [np.nan])
    pk = _assert_pack_equal(db, index)
    pk.lm_d *= 0.5
    db.unpack_states(pk)
    assert db.landmark(ids[0]).inv_dist == alive[ids[0]][1] * 0.5
    _assert_pack_equal(db, index, ids[::7])
    with pytest.raises(KeyError):
        db.pack(index, [id_base - 1])


def test_pack_with_spread_out_frame_ids_matches_reference():
    rng = np.random.default_rng(8)
    db = LandmarkDatabase()
    frames = [0, 7, 10**12, -3]
    for lm_id in range(40):
        db.add_landmark(lm_id, int(rng.choice(frames)), rng.normal(size=3) + [0, 0, 3], 0.5)
        for f in rng.choice(frames, size=3, replace=False).tolist():
            db.add_observation(lm_id, f, rng.uniform(0, 640, size=2), 1)
    index = {f: i for i, f in enumerate(frames)}
    _assert_pack_equal(db, index)
    _assert_pack_equal(db, index, list(range(39, -1, -3)), target_filter={7, 10**12})


def test_ids_by_host_are_the_hosted_sets_in_host_order():
    win = build_window(make_scene(num_frames=5, num_points=120))
    db = win.landmarks
    kfs = win.keyframe_ids
    for lm_id in list(db.landmark_ids)[::7]:  # holes in the id sequence and the store
        db.remove_landmark(lm_id)
    expected = [i for host in kfs for i in sorted(db.hosted_by(host))]
    assert len(expected) > 50
    assert db.ids_by_host(kfs).tolist() == expected
    assert db.ids_by_host(kfs[1:]).tolist() == [i for host in kfs[1:] for i in sorted(db.hosted_by(host))]


def test_landmark_points_are_the_hosts_points_in_world_and_in_a_camera():
    """Against the per-landmark definition: ``t_w_h + R_w_h bearing / d`` in the world, and
    mapped by ``T_x_w`` into another frame."""
    win = build_window(make_scene(num_frames=5, num_points=120), pose_noise=(0.1, 0.05))
    ids = np.array(win.landmarks.landmark_ids, dtype=np.int64)
    ids = ids[win.landmarks.inverse_distances(ids) > 0]
    expected = np.array([win.pose(win.landmarks.landmark(i).host_frame_id)[:3, 3]
                         + win.landmark_in_world(i)[0] / win.landmark_in_world(i)[1] for i in ids])
    assert len(ids) > 50 and len({win.landmarks.landmark(i).host_frame_id for i in ids}) > 1
    np.testing.assert_allclose(win.landmark_points(ids), expected, rtol=0, atol=1e-12)
    T_x_w = np.linalg.inv(win.pose(win.frame_ids[-1]))
    np.testing.assert_allclose(win.landmark_points(ids, T_x_w),
                               expected @ T_x_w[:3, :3].T + T_x_w[:3, 3], rtol=0, atol=1e-12)


def test_single_bearing_stereographic_parameter_has_the_bits_of_the_array_one():
    """The plain-float path used when a landmark is added gives exactly the array function's
    values (same operations in the same order), and rejects what it cannot represent."""
    from granite.backend.stereographic import stereo_from_bearing, stereo_from_bearing3

    rng = np.random.default_rng(11)
    b = rng.normal(size=(5000, 3)) * rng.uniform(0.01, 100.0, size=(5000, 1))
    b[:, 2] = np.abs(b[:, 2]) - 0.3 * np.abs(b[:, 0])  # some bearings point sideways or back
    b = b[b[:, 2] / np.linalg.norm(b, axis=1) > -1.0 + 1e-6]
    one = np.array([stereo_from_bearing3(v) for v in b])
    np.testing.assert_array_equal(one, stereo_from_bearing(b))
    with pytest.raises(ValueError):
        stereo_from_bearing3([0.0, 0.0, -2.0])
    with pytest.raises(ValueError):
        stereo_from_bearing3([0.0, 0.0, 0.0])


def test_scale_links_count_finite_landmarks_seen_in_two_other_keyframes():
    """Against a brute-force count over random observation sets: a landmark carries scale to a
    frame when it is finite and observed in at least two keyframes besides that frame."""
    rng = np.random.default_rng(21)
    db = LandmarkDatabase()
    frames = [0, 4, 9, 13, 14, 15]
    keyframes = [0, 4, 9, 13]
    seen = {}
    for lm_id in range(200):
        host = int(rng.choice(keyframes))
        d = 0.0 if rng.random() < 0.2 else float(rng.uniform(0.1, 2.0))
        db.add_landmark(lm_id, host, rng.normal(size=3) + [0, 0, 3], d)
        observers = {host} | set(rng.choice(frames, size=int(rng.integers(0, 4)), replace=False).tolist())
        for f in sorted(observers):
            db.add_observation(lm_id, f, rng.uniform(0, 640, size=2))
        seen[lm_id] = (d, observers)
    for frame in frames:
        expected = sum(1 for d, obs in seen.values()
                       if frame in obs and d > 0 and len((obs - {frame}) & set(keyframes)) >= 2)
        assert db.num_scale_links(frame, keyframes) == expected
    assert 0 < db.num_scale_links(15, keyframes) < len(db.observed_in(15))
    assert db.num_scale_links(15, keyframes[:1]) == 0  # one keyframe carries no scale
