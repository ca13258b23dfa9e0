"""The IK's polish phase: MuJoCo's exact contacts as residuals, and what they buy over the proxies."""

import numpy as np
import pytest

from embody.config.ik import IKConfig
from embody.retarget.exact_contacts import ExactContacts
from embody.retarget.ik import solve
from embody.robot.contacts import self_collision_contacts


@pytest.fixture(scope="module")
def robot():
    """The process's cached default robot (the library's own `load_robot`)."""
    from embody.robot import load_robot
    return load_robot()


def _hands_plant(robot):
    """Both wrists asked 10 cm apart in front of the chest: the hands would overlap."""
    from tests.test_retarget_ik import _targets_from_q

    targets = _targets_from_q(robot, np.tile(robot.rest, (4, 1)))
    targets.wrist_pos[:, 0] = [0.30, 0.05, 0.10]
    targets.wrist_pos[:, 1] = [0.30, -0.05, 0.10]
    return targets


def test_rows_are_margin_minus_distance_with_matching_jacobian(robot):
    targets = _hands_plant(robot)
    q = solve(robot, targets, IKConfig(w_collision=0.0, contact_repair=False)).q
    assert self_collision_contacts(robot, q).sum() > 0
    exact = ExactContacts(robot, margin=0.002, weight=4.0)
    r, jac = exact.rows(q)
    assert r.shape[0] == len(q) and jac.shape == (*r.shape, int(robot.ik_mask.sum()))
    assert r.max() > 2 * 0.002  # penetrating: √w·(margin − d) with d < 0
    assert (r >= 0).all()
    ik = np.flatnonzero(robot.ik_mask)
    rng = np.random.default_rng(0)
    step = rng.normal(size=len(ik)) * 1e-5
    qp, qm = q.copy(), q.copy()
    qp[:, ik] += step
    qm[:, ik] -= step
    # each pair's deepest row moves as its Jacobian row says (contact points may come and go)
    def deepest(qq):
        rr = exact.rows(qq)[0]
        return {(t, *exact.pairs[t, k]): rr[t, k] for t in range(len(qq)) for k in np.argsort(rr[t])
                if exact.pairs[t, k, 0] >= 0}

    base = {(t, *exact.pairs[t, k]): (r[t, k], jac[t, k]) for t in range(len(q)) for k in np.argsort(r[t])
            if exact.pairs[t, k, 0] >= 0}
    plus, minus = deepest(qp), deepest(qm)
    match = [np.isclose((plus[key] - minus[key]) / 2, row @ step, rtol=0.1, atol=1e-7)
             for key, (value, row) in base.items() if key in plus and key in minus and value > 0.005]
    # (a pair overlapping symmetrically, e.g. two thumbs nearly coincident, may flip its
    # penetration direction under any perturbation: a few rows need not match)
    assert len(match) >= 4 and np.mean(match) >= 0.75


def test_polish_tracks_closer_than_the_proxies_and_stays_clear(robot):
    targets = _hands_plant(robot)
    proxies = solve(robot, targets, IKConfig(contact_repair=False))
    polished = solve(robot, targets, IKConfig(polish_iterations=8, contact_repair=False))
    assert self_collision_contacts(robot, polished.q).sum() == 0  # no MuJoCo repair needed
    assert polished.metrics["wrist_pos_err_mm"] < proxies.metrics["wrist_pos_err_mm"] - 2.0
    # the narrowed MuJoCo model drops only pairs the verdict ignores or the IK cannot move
    exact = ExactContacts(robot, margin=0.0, weight=1.0)
    naive = solve(robot, targets, IKConfig(w_collision=0.0, contact_repair=False)).q
    r, _ = exact.rows(naive)
    assert ((r > 0).sum(1) > 0).tolist() == (self_collision_contacts(robot, naive) > 0).tolist()


def test_contact_phase_resolves_what_the_proxies_leak(robot):
    """Proxies without a margin let the planted hands penetrate (MuJoCo's verdict); the contact
    phase (`resolve_contacts`, MuJoCo's contacts as rows inside the LM) clears every frame, and
    `solve_joints` runs it by default."""
    from embody.retarget.ik import resolve_contacts, solve_joints

    targets = _hands_plant(robot)
    leaky = IKConfig(collision_margin=0.0, contact_rounds=0)
    q0 = solve_joints(robot, targets, leaky)
    assert (self_collision_contacts(robot, q0) > 0).all()
    on = IKConfig(collision_margin=0.0)
    q1 = resolve_contacts(robot, targets, on, q0)
    assert self_collision_contacts(robot, q1).sum() == 0
    np.testing.assert_array_equal(solve_joints(robot, targets, on), resolve_contacts(robot, targets, on, q0))
    # nothing to resolve: the trajectory comes back as it was
    clear = IKConfig()
    q2 = solve_joints(robot, targets, clear.model_copy(update={"contact_rounds": 0}))
    assert self_collision_contacts(robot, q2).sum() == 0
    np.testing.assert_array_equal(resolve_contacts(robot, targets, clear, q2), q2)


def _pose(robot, left, right, cfg):
    """One solved frame with the wrists asked at `left` / `right` (torso frame)."""
    from embody.retarget.ik import solve_joints
    from tests.test_retarget_ik import _targets_from_q

    targets = _targets_from_q(robot, np.tile(robot.rest, (4, 1)))
    targets.wrist_pos[:, 0], targets.wrist_pos[:, 1] = left, right
    return solve_joints(robot, targets, cfg)[0]


def test_contact_phase_is_local_and_hands_its_verdict_on(robot):
    """Hands overlapping on 4 frames of 40: the contact phase clears them, moves only the frames
    within `contact_window` (+ the held ones) of the contacts, and its verdict is MuJoCo's."""
    from embody.retarget.ik import HELD, resolve_contacts_checked
    from tests.test_retarget_ik import _targets_from_q

    clear = _pose(robot, [0.30, 0.15, 0.10], [0.30, -0.15, 0.10], IKConfig())
    planted = _pose(robot, [0.30, 0.05, 0.10], [0.30, -0.05, 0.10],
                    IKConfig(w_collision=0.0, contact_rounds=0))
    q = np.tile(clear, (40, 1))
    q[18:22] = planted
    assert (self_collision_contacts(robot, q) > 0).tolist() == [18 <= t < 22 for t in range(40)]
    cfg = IKConfig(contact_window=6)
    out, verdict = resolve_contacts_checked(robot, _targets_from_q(robot, q), cfg, q)
    assert self_collision_contacts(robot, out).sum() == 0
    np.testing.assert_array_equal(verdict, self_collision_contacts(robot, out) > 0)
    reach = 6 + HELD
    np.testing.assert_array_equal(out[: 18 - reach], q[: 18 - reach])  # outside the window: untouched
    np.testing.assert_array_equal(out[22 + reach:], q[22 + reach:])
    assert np.abs(out[18 - 6: 22 + 6] - q[18 - 6: 22 + 6]).max() > 1e-3


def test_contact_phase_resolves_a_pass_between_clear_frames(robot):
    """Left hand above the right, then below it: both frames clear, the control-rate samples
    between them (what the export resamples) have the hands inside each other. The contact phase
    finds and resolves them with `contact_samples`, and sees nothing without. (No velocity clamp
    here: the swap in one frame is faster than the arms may move, and the clamp would spread the
    pass over the frames themselves; see the next test.)"""
    from embody.retarget.ik import resolve_contacts_checked
    from embody.retarget.limits import resample

    q, targets = _swap(robot)
    free = IKConfig(enforce_velocity_limits=False)
    rate = free.control_rate_hz
    assert self_collision_contacts(robot, q).sum() == 0
    assert self_collision_contacts(robot, resample(q, targets.fps, rate)).sum() > 0
    off, verdict = resolve_contacts_checked(robot, targets, free.model_copy(update={"contact_samples": False}), q)
    np.testing.assert_array_equal(off, q)
    assert not verdict.any()
    out, verdict = resolve_contacts_checked(robot, targets, free, q)
    assert self_collision_contacts(robot, out).sum() == 0 and not verdict.any()
    assert self_collision_contacts(robot, resample(out, targets.fps, rate)).sum() == 0


def _swap(robot):
    """Left hand above the right for 6 frames, then below it for 6, each asked 3 cm past the
    midline (so the solved hands are in line, and pass through each other): q and its targets."""
    from tests.test_retarget_ik import _targets_from_q

    above = _pose(robot, [0.30, -0.03, 0.20], [0.30, 0.03, 0.0], IKConfig())
    below = _pose(robot, [0.30, -0.03, 0.0], [0.30, 0.03, 0.20], IKConfig())
    q = np.concatenate([np.tile(above, (6, 1)), np.tile(below, (6, 1))])
    return q, _targets_from_q(robot, q)


def test_contact_phase_judges_the_velocity_clamped_trajectory(robot):
    """The export clamps joint speeds after the IK, and the clamp alone can put hands through each
    other (here it spreads the one-frame swap over several frames): the contact phase judges and
    returns the clamped trajectory, clear of contacts at the frames and the 50 Hz samples."""
    from embody.retarget.ik import resolve_contacts_checked
    from embody.retarget.limits import clamp_velocity, resample, velocity_violations

    q, targets = _swap(robot)
    clamp = lambda x: clamp_velocity(x, robot.velocity_limits, targets.fps)  # noqa: E731
    assert self_collision_contacts(robot, q).sum() == 0
    assert self_collision_contacts(robot, clamp(q)).sum() > 0
    out, verdict = resolve_contacts_checked(robot, targets, IKConfig(), q)
    assert velocity_violations(out, robot.velocity_limits, targets.fps) == 0
    assert not verdict.any() and self_collision_contacts(robot, clamp(out)).sum() == 0
    assert self_collision_contacts(robot, resample(clamp(out), targets.fps, IKConfig().control_rate_hz)).sum() == 0


def test_sample_proxy_rows_give_the_samples_gradient(robot):
    """The proxies' rows at samples between frames (`Residuals._sample_rows`), split onto the two
    frames: their Gauss-Newton gradient Σ Jᵀr equals the gradient of ½‖r‖² over the samples'
    interpolated configurations (finite differences), and they ask only `contact_sample_margin`."""
    from embody.retarget.costs import Residuals
    from tests.test_retarget_ik import _targets_from_q

    q, _ = _swap(robot)
    q = q[4:8]  # above, above, below, below: the samples between frames 1 and 2 have the hands inside
    cfg = IKConfig()
    res = Residuals(robot, _targets_from_q(robot, q), cfg)
    ik = res.ik
    smp = (np.array([0, 1, 1, 2]), np.array([0.6, 0.4, 0.6, 0.4]))

    def rows(qq):
        qs = (1.0 - smp[1])[:, None] * qq[smp[0]] + smp[1][:, None] * qq[smp[0] + 1]
        rot, pos = res.fk.forward_once(qs)
        return res._sample_rows(len(qq), smp, rot, pos, 1.0), (rot, pos)

    (r, jac), (rot, pos) = rows(q)
    assert r.shape[0] == len(q) and (r > 0).any()
    # √(1 − α)·r and √α·r: the same cost as the samples' own rows, whose hinge is at the sample margin
    raw, _ = res._collision(rot, pos, 1.0)
    shift = res.w_col * (cfg.collision_margin - cfg.contact_sample_margin)
    np.testing.assert_allclose(0.5 * (r**2).sum(), 0.5 * (np.maximum(raw - shift, 0.0) ** 2).sum(), rtol=1e-12)
    g = np.einsum("tkj,tk->tj", jac(), r)  # (T, n_ik)

    def cost(qq):
        out = rows(qq)[0]
        return 0.5 * float((out[0] ** 2).sum()) if out is not None else 0.0

    rng = np.random.default_rng(1)
    d = rng.normal(size=(len(q), len(ik))) * 1e-6
    qp, qm = q.copy(), q.copy()
    qp[:, ik] += d
    qm[:, ik] -= d
    np.testing.assert_allclose((cost(qp) - cost(qm)) / 2.0, float((g * d).sum()), rtol=1e-3)


def test_sample_proxy_rows_packed_per_frame(robot):
    """`Residuals._sample_rows` keeps only the active (sample, proxy row) entries, packed per frame:
    each frame's rows are its samples' active rows scaled by √(1 − α) or √α, and the Gauss-Newton
    blocks JᵀJ and Jᵀr equal those of the full (sample × proxy row) layout."""
    from embody.retarget.costs import Residuals
    from tests.test_retarget_ik import _targets_from_q

    q, _ = _swap(robot)
    q = q[4:8]
    cfg = IKConfig()
    res = Residuals(robot, _targets_from_q(robot, q), cfg)
    smp = (np.array([0, 1, 1, 2]), np.array([0.6, 0.4, 0.6, 0.4]))
    qs = (1.0 - smp[1])[:, None] * q[smp[0]] + smp[1][:, None] * q[smp[0] + 1]
    rot, pos = res.fk.forward_once(qs)
    r, jac = res._sample_rows(len(q), smp, rot, pos, 1.0)
    j = jac()
    raw, raw_jac = res._collision(rot, pos, 1.0)
    shift = res.w_col * (cfg.collision_margin - cfg.contact_sample_margin)
    active = raw > shift
    js = raw_jac(*res.fk.joint_frames(rot, pos, list(res.ik))) * active[..., None]
    hinge = np.where(active, raw - shift, 0.0)
    jtj = np.zeros((len(q), j.shape[2], j.shape[2]))
    jtr = np.zeros((len(q), j.shape[2]))
    for k, (t, a) in enumerate(zip(*smp)):  # the full layout: every proxy row of every sample
        for f, w in ((t, 1.0 - a), (t + 1, a)):
            jtj[f] += w * js[k].T @ js[k]
            jtr[f] += w * js[k].T @ hinge[k]
    assert (r > 0).sum() == 2 * active.sum()  # each active entry once on each of its two frames
    assert r.shape[1] == np.bincount(np.r_[smp[0], smp[0] + 1], weights=np.r_[active.sum(1), active.sum(1)]).max()
    np.testing.assert_allclose(np.swapaxes(j, 1, 2) @ j, jtj, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose((np.swapaxes(j, 1, 2) @ r[..., None])[..., 0], jtr, rtol=1e-12, atol=1e-9)


def test_contact_phase_gives_up_when_the_deepest_contact_stalls(robot):
    """A contact the phase cannot move (here: MuJoCo's rows weigh nothing, so nothing pushes the
    hands apart) ends the round `contact_stall` LM evaluations after the deepest contact last
    improved, and no further round runs; with the stall off the same phase runs its budget."""
    from embody.retarget import ik as ikmod
    from embody.retarget.ik import resolve_contacts_checked
    from tests.test_retarget_ik import _targets_from_q

    planted = _pose(robot, [0.30, 0.05, 0.10], [0.30, -0.05, 0.10],
                    IKConfig(w_collision=0.0, contact_rounds=0))
    q = np.tile(planted, (12, 1))
    targets = _targets_from_q(robot, q)
    assert (self_collision_contacts(robot, q) > 0).all()
    calls: list[tuple[int, bool]] = []
    original = ikmod._Problem.evaluate

    def counted(self, *args, **kwargs):
        calls.append((id(self), bool(args[2] if len(args) > 2 else kwargs.get("exact", False))))
        return original(self, *args, **kwargs)

    weightless = IKConfig(w_contact=1e-12, contact_iterations=40, contact_rounds=3, tolerance=0.0,
                          contact_samples=False, contact_sample_proxies=False)
    try:
        ikmod._Problem.evaluate = counted
        out, verdict = resolve_contacts_checked(robot, targets, weightless.model_copy(update={"contact_stall": 4}), q)
        stalled = list(calls)
        calls.clear()
        resolve_contacts_checked(robot, targets, weightless.model_copy(update={"contact_stall": 0}), q)
        budget = list(calls)
    finally:
        ikmod._Problem.evaluate = original
    assert verdict.any()  # still touching: the repair's
    assert len({p for p, _ in stalled}) == 1  # one round
    assert len(stalled) == 1 + 4  # the start, then 4 evaluations without a better deepest contact
    assert len(budget) > 2 * len(stalled)


def test_a_round_with_clear_rows_is_not_a_stall(robot):
    """A contact round whose MuJoCo rows see no penetration while its verdict (`clear`) still
    fails (the velocity clamp moved a pose the rows judged clear into contact) ends after
    `contact_stall` evaluations without marking the phase stalled: the next round, from the
    clamped q, sees the contact. With the rows penetrating and not improving it is a stall."""
    from embody.retarget.ik import _Problem
    from tests.test_retarget_ik import _targets_from_q

    cfg = IKConfig(contact_stall=4, contact_iterations=40, tolerance=0.0, contact_sample_proxies=False)
    apart = _pose(robot, [0.30, 0.15, 0.10], [0.30, -0.15, 0.10], IKConfig())
    planted = _pose(robot, [0.30, 0.05, 0.10], [0.30, -0.05, 0.10],
                    IKConfig(w_collision=0.0, contact_rounds=0))
    outcomes = []
    for q, weight in ((np.tile(apart, (6, 1)), cfg.w_contact), (np.tile(planted, (6, 1)), 1e-12)):
        problem = _Problem(robot, _targets_from_q(robot, q), cfg.model_copy(update={"polish_iterations": 0}))
        problem.residuals.exact = ExactContacts(robot, cfg.contact_margin, weight)
        problem.solve(q[:, problem.ik], cold=False, contact_frames=np.ones(len(q), bool),
                      clear=lambda qi: False)
        outcomes.append((problem.residuals.exact.deepest, problem.stalled))
    (clear_deepest, clear_stalled), (deep, deep_stalled) = outcomes
    assert clear_deepest >= 0 and not clear_stalled
    assert deep < 0 and deep_stalled


def test_rows_stop_early_only_past_the_limit(robot):
    """`ExactContacts.rows(limit=)`: None only when the rows' sum of squares is above the limit
    (the LM trial it serves is rejected either way); under it, the same rows bit for bit."""
    targets = _hands_plant(robot)
    q = solve(robot, targets, IKConfig(w_collision=0.0, contact_repair=False)).q
    exact = ExactContacts(robot, margin=0.002, weight=4.0)
    r, jac = exact.rows(q)
    total = float((r**2).sum())
    assert total > 0
    r2, jac2 = exact.rows(q, limit=total * (1 + 1e-9))
    assert np.array_equal(r, r2) and np.array_equal(jac, jac2)
    assert exact.rows(q, limit=total * 0.5) is None


def test_exact_rows_keep_the_proxy_block_only_as_wide_as_the_proxy_frames(robot):
    """`Residuals._exact_rows`: the proxies' block is zero on MuJoCo's frames, so it is cut to the
    widest of the other frames' packed rows; what is cut is zero in the rows and the Jacobian, and
    the rest is the full layout's, bit for bit."""
    from embody.retarget.costs import Residuals
    from tests.test_retarget_ik import _targets_from_q

    overlap = solve(robot, _hands_plant(robot), IKConfig(w_collision=0.0, contact_repair=False)).q
    q = np.concatenate([overlap[:2], np.tile(robot.rest, (2, 1))])  # hands inside each other, then rest
    res = Residuals(robot, _targets_from_q(robot, q), IKConfig())
    res.exact = ExactContacts(robot, 0.002, 1000.0)
    res.exact.frames = np.array([True, True, False, False])
    rot, pos = res.fk.forward(q)
    col = res._collision(rot, pos, 1.0)
    r, jacobian = res._exact_rows(q, col)
    z, o = res.fk.joint_frames(rot, pos, list(res.ik))
    j = jacobian(z, o)
    r_ex, j_ex = res.exact.rows(q)
    n_px = r.shape[1] - r_ex.shape[1]
    full_r = np.where(res.exact.frames[:, None], 0.0, col[0])
    full_j = col[1](z, o)
    full_j[res.exact.frames] = 0.0
    assert 0 < n_px < col[0].shape[1]  # the overlapping hands' frames had more proxy rows
    assert not full_r[:, n_px:].any() and not full_j[:, n_px:].any()
    assert np.array_equal(r[:, :n_px], full_r[:, :n_px]) and np.array_equal(j[:, :n_px], full_j[:, :n_px])
    assert np.array_equal(r[:, n_px:], r_ex) and np.array_equal(j[:, n_px:], j_ex)


def test_trial_rows_deepest_pose_first_same_rows(robot):
    """A trial (`rows(limit=)`) asks MuJoCo about the poses that were deepest at the last call
    first, so a trial that cannot win stops after them; the rows do not depend on that order
    (frames and samples between them, bit for bit the plain call's)."""
    targets = _hands_plant(robot)
    q = solve(robot, targets, IKConfig(w_collision=0.0, contact_repair=False)).q
    exact = ExactContacts(robot, margin=0.002, weight=4.0)
    exact.between = (np.array([0, 1, 2]), np.array([0.4, 0.2, 0.8]))
    r, jac = exact.rows(q)
    total = float((r**2).sum())
    weight = exact._weight[1].copy()
    assert weight.shape == (4 + 3,) and weight.max() > 0
    calls = []
    original = exact._contacts
    exact._contacts = lambda x, t, scale, tag, found: (calls.append((t, tag)), original(x, t, scale, tag, found))
    r2, jac2 = exact.rows(q, limit=total * (1 + 1e-9))  # reordered, every pose asked: the same rows
    assert np.array_equal(r, r2) and np.array_equal(jac, jac2)
    deepest = int(np.argmax(weight))
    assert calls[0] == ((deepest, 0) if deepest < 4 else (int(exact.between[0][deepest - 4]), 1 + 2 * (deepest - 4)))
    calls.clear()
    assert exact.rows(q, limit=0.0) is None
    assert len(calls) == 1  # the deepest pose alone passes a zero limit
    exact.between = None  # other poses: the plain order again
    r3, _ = exact.rows(q, limit=1e9)
    assert np.array_equal(r3, exact.rows(q)[0])


def test_trials_skipped_on_a_bound_keep_the_cost(robot):
    """`_Problem.evaluate(bound=)`: a trial comes back as inf only when its cost is above the
    bound; otherwise its cost is the unbounded evaluation's, bit for bit (so the solver accepts
    and rejects the same steps)."""
    from embody.retarget.ik import _Problem

    targets = _hands_plant(robot)
    problem = _Problem(robot, targets, IKConfig())
    rng = np.random.default_rng(4)
    q0 = solve(robot, targets, IKConfig(contact_repair=False)).q[:, problem.ik]
    checked = skipped = 0
    for scale in (0.0, 0.01, 0.1, 0.5):
        qi = np.clip(q0 + rng.normal(0.0, scale, q0.shape), robot.lower[problem.ik], robot.upper[problem.ik])
        for exact in (False, True):
            if exact:
                problem.residuals.exact = ExactContacts(robot, 0.002, 1000.0)
                problem.residuals.exact.frames = np.ones(len(qi), bool)
            cost, _ = problem.evaluate(qi, 1.0, exact)
            for bound in (cost * 0.5, cost * (1 - 1e-6), cost * (1 + 1e-6), cost * 2):
                c, normal = problem.evaluate(qi, 1.0, exact, bound=bound)
                if c == np.inf:
                    assert cost > bound and normal is None
                    skipped += 1
                else:
                    assert c == cost
                    checked += 1
    assert checked >= 8 and skipped >= 4
