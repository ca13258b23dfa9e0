"""Fidelity metrics on built cases: identical motion → 0, a known offset → that error, a known
contact → recall 1, a penetrating robot contact does not count."""

from __future__ import annotations

import numpy as np
import pytest

from embody.body.landmarks import LANDMARKS
from embody.metrics.fidelity import CONTACTS, Track, compare


def _track(seed: int = 0, t: int = 30, scale: float = 0.3, spin: float = 0.0) -> Track:
    """A made-up body: fixed landmarks, palms moving on smooth paths, torso turned by `spin`."""
    rng = np.random.default_rng(seed)
    rest = rng.normal(size=(len(LANDMARKS), 3)) * scale
    for side in ("left", "right"):  # ring and pinky as the middle finger: the 5→3 mapping is exact
        for f in ("ring", "pinky"):
            rest[LANDMARKS.index(f"{side}_{f}_tip")] = rest[LANDMARKS.index(f"{side}_middle_tip")]
    points = np.repeat(rest[None], t, 0).copy()
    s = np.linspace(0, 1, t)[:, None]
    for side in ("left", "right"):
        i = LANDMARKS.index(f"{side}_palm")
        points[:, i] = rest[LANDMARKS.index("chin")] + 0.05 * np.hstack([np.sin(6 * s), s, np.cos(3 * s)])
    c, si = np.cos(spin), np.sin(spin)
    rot = np.array([[c, -si, 0], [si, c, 0], [0, 0, 1]])
    torso = np.repeat(rot[None], t, 0)
    normals = np.repeat(np.array([[0, 0, -1.0], [0, 0, -1.0]])[None], t, 0)
    contact = np.full((t, len(CONTACTS)), 0.1)
    return Track(names=LANDMARKS, points=points @ rot.T, normals=normals @ rot.T, torso=torso,
                 scale=scale, rest=rest @ rot.T, contact=contact)


def test_identical_motion_scores_zero():
    h = _track()
    r = _track(spin=0.7)  # same body turned: every measure is in the torso frame
    _, m = compare(h, r)
    for key in ("location_err", "palm_deg", "pointing_deg", "handshape_err", "movement_dtw"):
        assert m[key] == pytest.approx(0.0, abs=1e-6), key
    assert m["location_agree_pct"] == 100.0 and m["path_ratio"] == pytest.approx(1.0)
    assert m["speed_corr"] == pytest.approx(1.0)
    assert np.isnan(m["contact_f1"]) and m["penetration_frames"] == 0


def test_known_offset_gives_that_error_in_body_scales():
    h = _track()
    r = _track(scale=0.3)
    r.scale = 0.24  # a smaller robot: distances compare per body scale
    r.points = r.points * 0.8
    r.rest = r.rest * 0.8
    shift = np.array([0.0, 0.0, -0.08])  # the robot's right palm 8 cm too low
    r.points[:, LANDMARKS.index("right_palm")] += shift
    _, m = compare(h, r)
    # left palm exact, right palm off by 0.08 / 0.24 scales: mean over hands
    assert m["location_err"] == pytest.approx(0.5 * 0.08 / 0.24, rel=1e-6)
    assert m["location_err_mm"] == pytest.approx(0.5 * 80.0, rel=1e-6)


def test_palm_orientation_error():
    h, r = _track(), _track()
    r.normals = r.normals.copy()
    r.normals[:, 1] = [0.0, np.sin(np.radians(30)), -np.cos(np.radians(30))]
    _, m = compare(h, r)
    assert m["palm_deg"] == pytest.approx(15.0, abs=1e-6)  # 30° on one hand of two


def test_known_contact_gives_recall_one_and_penetration_does_not_count():
    h, r = _track(), _track()
    h.contact[10:20, CONTACTS.index("right_face")] = 0.005  # the human touches its face
    r.contact[10:20, CONTACTS.index("right_face")] = 0.0
    _, m = compare(h, r)
    assert m["contact_recall"] == 1.0 and m["contact_precision"] == 1.0 and m["contact_f1"] == 1.0
    r.contact[10:15, CONTACTS.index("right_face")] = -0.01  # half of it through the face
    _, m = compare(h, r)
    assert m["contact_recall"] == 0.5 and m["penetration_frames"] == 5
    r.contact[:, :] = 0.1  # the robot never touches
    _, m = compare(h, r)
    assert m["contact_recall"] == 0.0 and m["contact_f1"] == 0.0


def test_handshape_flexion_error():
    h, r = _track(), _track()
    i, p = LANDMARKS.index("right_index_tip"), LANDMARKS.index("right_palm")
    r.points = r.points.copy()
    # robot index tip pulled halfway to the palm: flexion 0.5 vs the human's straight finger
    r.points[:, i] = r.points[:, p] + 0.5 * (r.rest[i] - r.rest[p])
    _, m = compare(h, r)
    # human flexion: its palm moved away from rest, so compute the expected value directly
    from embody.metrics.fidelity import flexion
    expected = np.abs(flexion(h, "right", "index") - 0.5).mean() / 6  # 1 of 6 finger slots
    assert m["handshape_err"] == pytest.approx(expected, abs=1e-9)


def test_resampled_track_lies_on_the_exported_control_grid():
    """The human side of a comparison with the exported array: same sample count and times as
    `control_trajectory`'s resampling, linear paths reproduced exactly, rotations kept rotations."""
    from embody.metrics.fidelity import resample_track
    from embody.retarget.limits import resample

    h = _track(t=31)
    h.fps = 30.0
    spin = np.linspace(0.0, 1.0, 31)  # torso turning 1 rad over the second
    c, s = np.cos(spin), np.sin(spin)
    h.torso = np.stack([np.stack([c, -s, 0 * c], -1), np.stack([s, c, 0 * c], -1),
                        np.stack([0 * c, 0 * c, 1 + 0 * c], -1)], 1)
    chin = LANDMARKS.index("chin")
    h.points[:, chin] = np.linspace(0.0, 0.3, 31)[:, None] * [1.0, 0.0, 0.0]
    h.contact[:, 2] = np.linspace(0.0, 0.03, 31)
    r = resample_track(h, 50.0)
    grid = resample(np.zeros((31, 1)), 30.0, 50.0)
    assert len(r.points) == len(grid) == 51 and r.fps == 50.0
    t = np.arange(51) / 50.0
    np.testing.assert_allclose(r.points[:, chin, 0], 0.3 * t, atol=1e-12)
    np.testing.assert_allclose(r.contact[:, 2], 0.03 * t, atol=1e-12)
    np.testing.assert_allclose(r.torso @ np.swapaxes(r.torso, 1, 2), np.tile(np.eye(3), (51, 1, 1)), atol=1e-12)
    angle = np.arctan2(r.torso[:, 1, 0], r.torso[:, 0, 0])
    np.testing.assert_allclose(angle, t, atol=2e-4)  # chord interpolation of a 1/30 rad step
    np.testing.assert_allclose(np.linalg.norm(r.normals, axis=-1), 1.0)


def _two_landmark_track(palm: np.ndarray, scale: float = 0.3) -> Track:
    """Mouth at (0,0,0), chin 3 cm below, every other landmark far away; both palms at `palm`."""
    t = len(palm)
    rest = np.tile(np.array([5.0, 5.0, 5.0]), (len(LANDMARKS), 1)) + np.arange(len(LANDMARKS))[:, None]
    rest[LANDMARKS.index("mouth")] = 0.0
    rest[LANDMARKS.index("chin")] = (0.0, 0.0, -0.03)
    points = np.repeat(rest[None], t, 0).copy()
    for side in ("left", "right"):
        points[:, LANDMARKS.index(f"{side}_palm")] = palm
    normals = np.repeat(np.array([[0, 0, -1.0], [0, 0, -1.0]])[None], t, 0)
    return Track(names=LANDMARKS, points=points, normals=normals, torso=np.repeat(np.eye(3)[None], t, 0),
                 scale=scale, rest=rest)


def test_location_agreement_counts_ties_between_close_landmarks_only():
    # the human palm 8 cm in front of mouth and chin, a hair nearer the mouth
    h = _two_landmark_track(np.tile([0.08, 0.0, -0.014], (4, 1)))
    # the robot palm a hair nearer the chin: a tie, not a different location
    r = _two_landmark_track(np.tile([0.08, 0.0, -0.016], (4, 1)))
    _, m = compare(h, r, radius=0.5, tie=0.05)
    assert m["location_agree_pct"] == 100.0 and m["location_agree_exact_pct"] == 0.0
    # the human palm 1 cm above the mouth, the robot's 1 cm below the chin: no tie
    h = _two_landmark_track(np.tile([0.0, 0.0, 0.01], (4, 1)))
    r = _two_landmark_track(np.tile([0.0, 0.0, -0.04], (4, 1)))
    frames, m = compare(h, r, radius=0.5, tie=0.05)
    assert m["location_agree_pct"] == 0.0 and not frames["location_agree"].any()
    # without a tolerance the near-tie disagrees too
    h = _two_landmark_track(np.tile([0.08, 0.0, -0.014], (4, 1)))
    r = _two_landmark_track(np.tile([0.08, 0.0, -0.016], (4, 1)))
    _, m = compare(h, r, radius=0.5, tie=0.0)
    assert m["location_agree_pct"] == 0.0


def test_contact_events_match_when_runs_overlap():
    from embody.metrics.fidelity import contact_events, event_f1

    h = np.zeros((20, 2), dtype=bool)
    r = np.zeros((20, 2), dtype=bool)
    h[3:8, 0] = True   # one touch, the robot's 2 frames late: found, and right
    r[5:10, 0] = True
    h[12:15, 0] = True  # a touch the robot misses
    r[15:18, 1] = True  # a robot touch in another channel: wrong
    ev = contact_events(h, r)
    assert ev == {"human": 2, "robot": 2, "found": 1, "right": 1}
    p, rc, f = event_f1(ev)
    assert (p, rc, f) == (0.5, 0.5, 0.5)


def test_human_contacts_are_the_least_mesh_distances_capped_at_reach():
    """`human_contacts` (broad phase per chunk, a KD-tree of the nearby hand points) gives the
    brute-force least vertex distance between each channel's parts, capped at its reach."""
    import torch
    from scipy.spatial.distance import cdist

    from embody.body import load_body_model
    from embody.metrics import embodiments as emb
    from embody.synth import generate_sequence

    body = load_body_model()
    m = generate_sequence(0, 7)
    betas = np.asarray(m.betas, dtype=np.float64)
    frames = np.arange(0, m.num_frames, 6)
    with torch.no_grad():
        tr = body.joint_transforms(torch.as_tensor(np.asarray(m.pose)[frames], dtype=torch.float64),
                                   torch.as_tensor(betas)).numpy()
    channels = ("left_chest", "hands", "right_face")  # any subset, in the order asked
    got = emb.human_contacts(body, tr, betas, channels)
    sets = emb._vertex_sets(body)
    with torch.no_grad():
        verts = body.vertices(torch.as_tensor(np.asarray(m.pose)[frames], dtype=torch.float64),
                              torch.as_tensor(betas)).numpy()
    pairs = {"hands": ("left_hand", "right_hand"), "left_chest": ("left_hand", "chest"),
             "right_face": ("right_hand", "face")}
    want = np.array([[min(cdist(v[sets[pairs[c][0]]], v[sets[pairs[c][1]]]).min(), emb._REACH)
                      for c in channels] for v in verts])
    assert got.shape == (len(frames), 3)
    assert (want < emb._REACH).any()  # some frames in contact range: the narrow phase is tested
    np.testing.assert_allclose(got, want, atol=1e-6)


def test_subset_skin_is_the_bodys_own_skinning():
    """The contact measure's skinning of a vertex subset (one product of a per-vertex table and
    the frames' bones) gives the body model's vertices, in float64 (to 1e-7 m: the body sums its
    blend in another order; the float32 blend before was 1.7e-7 off)."""
    import torch

    from embody.body import load_body_model
    from embody.metrics import embodiments as emb
    from embody.synth import generate_sequence

    body = load_body_model()
    m = generate_sequence(0, 3)
    betas = np.asarray(m.betas, dtype=np.float64)
    pose = torch.as_tensor(np.asarray(m.pose)[::9], dtype=torch.float64)
    subset = np.concatenate(list(emb._vertex_sets(body).values()))
    with torch.no_grad():
        tr = body.joint_transforms(pose, torch.as_tensor(betas)).numpy()
        want = body.vertices(pose, torch.as_tensor(betas)).numpy()[:, subset]
    got = emb._SubsetSkin(body, betas, subset)(tr)
    assert got.shape == want.shape and got.dtype == np.float64
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-7)


def test_human_contacts_remember_each_shape_exactly():
    """The subset skin is made once per body and shape (`_contact_skin`): a second call gives the
    same distances bit for bit, and another shape gets its own skin, not the first one's."""
    import torch

    from embody.body import load_body_model
    from embody.metrics import embodiments as emb
    from embody.synth import generate_sequence

    body = load_body_model()
    m = generate_sequence(0, 7)
    pose = torch.as_tensor(np.asarray(m.pose)[::6], dtype=torch.float64)
    a = np.asarray(m.betas, dtype=np.float64)
    b = a + 1.0  # another body shape
    with torch.no_grad():
        tr_a, tr_b = (body.joint_transforms(pose, torch.as_tensor(x)).numpy() for x in (a, b))
    emb._SKINS.clear()
    fresh_b = emb.human_contacts(body, tr_b, b)
    emb._SKINS.clear()
    first = emb.human_contacts(body, tr_a, a)
    assert np.array_equal(emb.human_contacts(body, tr_a, a), first)
    assert np.array_equal(emb.human_contacts(body, tr_b, b), fresh_b)
    assert emb._contact_skin(body, a)[1] is emb._contact_skin(body, a.copy())[1]
    # the shape matters to the skin, so serving a's skin for b would be seen above
    subset = emb._contact_skin(body, a)[1]
    assert not np.array_equal(subset(tr_b), emb._contact_skin(body, b)[1](tr_b))


def test_human_contacts_remembered_per_sequence_and_root_free():
    """A remembered table serves any channel subset, in the order asked, bit for bit as a fresh
    measure; the human track measures relative to the pelvis, which moves no mesh distance
    (beyond rounding)."""
    import torch

    from embody.body import load_body_model
    from embody.metrics import embodiments as emb
    from embody.synth import generate_sequence

    body = load_body_model()
    m = generate_sequence(0, 7)
    m.pose[:, 0] = np.array([0.3, -0.5, 0.2])  # a root rotation and translation to leave out
    m.transl[:] = np.array([0.1, 0.9, -0.4])
    betas = np.asarray(m.betas, dtype=np.float64)
    rel = emb.rootless_transforms(m, body)
    fresh = emb._human_contacts(body, rel, betas)
    emb._CONTACTS_MEMO.clear()
    channels = ("right_face", "hands")
    first = emb.human_contacts(body, rel, betas, channels)
    again = emb.human_contacts(body, rel.copy(), betas, channels)
    want = fresh[:, [CONTACTS.index(c) for c in channels]]
    assert np.array_equal(first, want) and np.array_equal(again, want)
    again[:] = -1.0  # the caller's copy: the remembered table is not changed
    assert np.array_equal(emb.human_contacts(body, rel, betas), fresh)
    track = emb.human_track(m, body)
    assert np.array_equal(track.contact, fresh)
    with torch.no_grad():
        rooted = body.joint_transforms(torch.as_tensor(m.pose, dtype=torch.float64), torch.as_tensor(betas),
                                       torch.as_tensor(m.transl, dtype=torch.float64)).numpy()
    # the same distances up to the body model's float32 rest shape (~2e-8 m here)
    np.testing.assert_allclose(emb._human_contacts(body, rooted, betas), fresh, rtol=0, atol=1e-7)
    assert (fresh < emb._REACH).any()  # some contact in range: the comparison says something
