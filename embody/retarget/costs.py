"""IK tasks as weighted residuals with analytic Jacobians, for every frame at once (NumPy).

One residual vector per frame, r_t = [√w·(p − p*) for wrists and elbows, √w·log(R R*ᵀ) for the
wrists (and torso/head when weighted), √w·relu(margin − clearance) for near proxy pairs,
√w·(p − a) for anchored hand points (`hand_points.py`)]; wrist weights are per frame. The
posture prior and the Δ²q smoothness are linear and handled by the solver. Jacobians are
geometric: for a hinge j with torso-frame axis z and pivot o, ∂p/∂q_j = z × (p − o) and the
rotation error moves by z (exact at zero error, which is where Gauss-Newton needs it), for
every point or frame downstream of j. One FK pass (`cfg.kinematics`: pytorch-kinematics or
the NumPy tree, `embody.robot.fk`) feeds everything.

More tasks slot in as `ResidualTerm`s (a list: `Residuals(..., terms=[...])`, or every solve
through `extra_terms`): each names the bodies it reads, gets the FK pass, and returns its rows and
their Jacobian from the joint axes and pivots, appended after the built-in rows.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from embody.config.ik import IKConfig
from embody.retarget.exact_contacts import ExactContacts
from embody.retarget.hand_clearance import hand_clearance_term
from embody.retarget.hand_points import hand_point_term
from embody.retarget.jacobians import cross, normal_jacobian
from embody.retarget.proxy_hulls import Contacts, HullTables, hull_contacts, plane_table
from embody.retarget.targets import Targets
from embody.robot import Robot
from embody.robot.fk import rotate
from embody.robot.proxies import robot_proxies

WRIST_ELBOW = ["left_wrist", "right_wrist", "left_elbow", "right_elbow"]


@dataclass
class Pose:
    """One FK pass of every frame: torso-frame rotations (T,B,3,3) and positions (T,B,3) of the
    FK bodies (`index[name]` → B column) and which IK joint moves which body (`mask` (J,B))."""

    rot: np.ndarray
    pos: np.ndarray
    index: dict[str, int]
    mask: np.ndarray


#: Jacobian of a term's rows from the IK joints' world axes z and pivots o (both (T,J,3)) → (T,m,J).
TermJacobian = Callable[[np.ndarray, np.ndarray], np.ndarray]


class ResidualTerm:
    """A block of per-frame residual rows for the IK (subclass it; see the module docstring)."""

    #: MuJoCo body names whose transforms `rows` reads (added to the FK pass).
    bodies: list[str] = []

    def rows(self, pose: Pose, scale: float) -> tuple[np.ndarray, TermJacobian] | None:
        """Residuals (T,m) and their Jacobian; `scale` is the solver's collision phase factor
        (1 in the full phase), which a term may ignore. None: no rows this time."""
        raise NotImplementedError


def point_jacobian(z: np.ndarray, o: np.ndarray, p: np.ndarray, moves: np.ndarray) -> np.ndarray:
    """∂p/∂q (T,P,3,J) of points p (T,P,3) rigidly attached to bodies moved per `moves` (J,P)."""
    return cross(z[:, None], p[:, :, None] - o[:, None]).transpose(0, 1, 3, 2) * moves.T[None, :, None]


def extra_terms(robot: Robot, targets: Targets, cfg: IKConfig) -> list[ResidualTerm]:
    """Residual terms every solve adds to the built-in ones (the hook for new IK tasks): the
    anchored hand points of location-preserving targets (`hand_points.py`) and their hand-hand
    clearance (`hand_clearance.py`)."""
    terms = [hand_point_term(robot, targets, cfg.w_hand_points),
             hand_clearance_term(robot, targets, cfg.w_hand_clearance)]
    return [t for t in terms if t is not None]


def rotation_log(r: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of rotation matrices (..., 3, 3) (angle < π)."""
    v = 0.5 * np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], -1)
    cos = np.clip((np.einsum("...ii->...", r) - 1.0) / 2.0, -1.0, 1.0)
    sin = np.linalg.norm(v, axis=-1)
    angle = np.arctan2(sin, cos)
    scale = np.where(sin > 1e-9, angle / np.maximum(sin, 1e-300), 1.0)
    return v * scale[..., None]


class Residuals:
    """r(q) (T,m) and J = ∂r/∂q_ik (T,m,n_ik) for a sequence's targets."""

    def __init__(self, robot: Robot, targets: Targets, cfg: IKConfig,
                 terms: list[ResidualTerm] | None = None) -> None:
        self.robot, self.cfg = robot, cfg
        self.ik = np.flatnonzero(robot.ik_mask)
        self.terms = list(terms or []) + extra_terms(robot, targets, cfg)
        term_bodies = sorted({b for term in self.terms for b in term.bodies})
        self.rot_links = [n for n, w in (("spine3", cfg.w_torso_rot), ("head", cfg.w_head_rot))
                          if n in robot.spec.links and w > 0]
        links = WRIST_ELBOW + self.rot_links
        self.proxies = robot_proxies(robot) if cfg.w_collision > 0 and robot.spec.proxy_pairs else None
        refs = [robot.spec.links[n] for n in links]
        self.link_offset = np.array([r.offset for r in refs])
        self.rot_cols = [0, 1] + list(range(4, 4 + len(self.rot_links)))
        key = ("ik_geometry", tuple(links), tuple(term_bodies), self.proxies is not None, cfg.kinematics)
        if key not in robot.derived:  # the static part, once per robot and task set
            robot.derived[key] = self._geometry(robot, [r.body for r in refs], cfg.kinematics, term_bodies)
        for name, value in robot.derived[key].items():
            setattr(self, name, value)
        if self.proxies is not None:
            px = self.proxies
            # per group member: how far from its hull's box centre it may be, per axis
            half = (px.hull_box[:, 1] - px.hull_box[:, 0]) / 2
            radii = np.where(self.group_members >= 0, px.radii[px.hull_pairs[self.group_members, 0]], -np.inf)
            reach = half[self.group_hull][:, None] + (cfg.collision_margin + radii)[..., None]
            self.hulls = HullTables(
                part_body=self.part_body, part_centre=self.part_centre, hull_body=self.hull_body,
                hull_centre=px.hull_centre, group_part=self.group_part, group_hull=self.group_hull,
                group_reach=self.part_radius[self.group_part] + px.hull_radius[self.group_hull] + cfg.collision_margin,
                group_box_reach=self.part_radius[self.group_part] + cfg.collision_margin,
                group_members=self.group_members,
                # axis-major (G,3,M): the NumPy reference's per-point test is one batched matmul
                member_centres_t=np.ascontiguousarray(
                    np.swapaxes(px.centres[px.hull_pairs[self.group_members, 0]], 1, 2)),
                member_reach_t=np.ascontiguousarray(np.swapaxes(reach, 1, 2)),
                box_mid=self.box_mid, box_half=half, hull_planes=self.hull_planes,
                plane_table=self.plane_table, plane_count=self.plane_count,
                pair_sphere=px.hull_pairs[:, 0], pair_hull=px.hull_pairs[:, 1],
                pair_radius=px.radii[px.hull_pairs[:, 0]])
        self.target_pos = np.concatenate([targets.wrist_pos, targets.elbow_pos], 1).astype(np.float64)
        rots = [np.asarray(targets.wrist_rot, dtype=np.float64)]
        rots += [np.asarray(targets.torso_rot if n == "spine3" else targets.head_rot, dtype=np.float64)[:, None]
                 for n in self.rot_links]
        self.target_rot = np.concatenate(rots, 1)  # (T,2+k,3,3)
        s = np.sqrt
        self.w_pos = np.array([s(cfg.w_wrist_pos)] * 2 + [s(cfg.w_elbow_pos)] * 2)
        self.w_rot = np.array([s(cfg.w_wrist_rot)] * 2 + [s(cfg.w_torso_rot if n == "spine3" else cfg.w_head_rot)
                                                          for n in self.rot_links])
        # per frame (T,·): the wrist position lets go where an anchored hand point carries the
        # sign; its rotation holds on harder (any point target is reachable at the human's palm
        # orientation by moving the wrist; released, the points twisted palms by 30-70 degrees)
        keep = np.sqrt(np.asarray(targets.wrist_weight, dtype=np.float64))  # (T,2)
        self.w_pos = self.w_pos * np.concatenate([keep, np.ones_like(keep)], 1)
        hold = np.sqrt(np.asarray(targets.wrist_rot_weight, dtype=np.float64))  # (T,2), > 1 at a touch
        self.w_rot = self.w_rot * np.concatenate([hold, np.ones((len(hold), len(self.rot_links)))], 1)
        self.w_col = float(s(cfg.w_collision))
        #: (frame, fraction) arrays of samples between frames where the exact phase also puts the
        #: proxies' rows (`_sample_rows`); None: none
        self.sample_points: tuple[np.ndarray, np.ndarray] | None = None
        self.exact = (ExactContacts(robot, cfg.polish_margin, cfg.w_collision)
                      if self.proxies is not None and cfg.polish_iterations else None)

    def __call__(self, q: np.ndarray, jacobian: bool = False,
                 collision: float = 1.0) -> tuple[np.ndarray, np.ndarray | None]:
        """q: full joint vectors (T, n_joints). `collision` scales w_collision (0/False: term left out)."""
        r, jac = self.lazy(q, collision)
        return r, (jac() if jacobian else None)

    def lazy(self, q: np.ndarray, collision: float = 1.0, exact: bool = False,
             limit: float | None = None) -> tuple[np.ndarray | None, Callable[[], np.ndarray] | None]:
        """r(q) now, J(q) on demand: a rejected step never pays for its Jacobian. `exact`: the
        polish phase's collision rows, MuJoCo's own contacts (`exact_contacts.py`), replace the
        proxies'. `limit`: (None, None) as soon as the rows computed so far have a sum of squares
        above it, before the costlier blocks (the proxies, the other terms, MuJoCo last): the LM
        solver's trial that cannot beat its current cost skips them (each block is a sum of
        squares, so the rows left out only add to it)."""
        rot, pos = self.fk.forward(q)
        r_link = rot[:, self.link_body]
        p_link = pos[:, self.link_body] + np.einsum("tlab,lb->tla", r_link, self.link_offset)
        e_pos = (p_link[:, :4] - self.target_pos) * self.w_pos[..., None]
        r_rot = r_link[:, self.rot_cols]
        e_rot = rotation_log(r_rot @ np.swapaxes(self.target_rot, -1, -2)) * self.w_rot[..., None]
        res = [e_pos.reshape(len(q), -1), e_rot.reshape(len(q), -1)]
        self.n_task_rows = sum(x.shape[1] for x in res)  # rows before the collision rows
        total = 0.0

        def over(*blocks: np.ndarray) -> bool:
            nonlocal total
            if limit is None:
                return False
            total += sum(float((b**2).sum()) for b in blocks)
            return total > limit

        if over(*res):
            return None, None
        col = self._collision(rot, pos, float(collision)) if self.proxies is not None and collision else None
        exact = exact and self.exact is not None and col is not None
        if col is not None and limit is not None:  # the proxies' rows that stay (not on MuJoCo's frames)
            kept = col[0] if not exact else (np.zeros(0) if self.exact.frames is None else
                                             np.where(self.exact.frames[:, None], 0.0, col[0]))
            if over(kept):
                return None, None
        extra = []
        if self.terms:
            pose = Pose(rot, pos, self.fk.index, self.mask)
            extra = [out for out in (term.rows(pose, float(collision)) for term in self.terms) if out is not None]
            if over(*(r for r, _ in extra)):
                return None, None
        if exact:  # MuJoCo's rows (and the proxies' at the samples between frames) last: the costliest
            smp = self.sample_points
            samples = None
            if smp is not None and len(smp[0]):
                t_s, a_s = smp
                qs = (1.0 - a_s)[:, None] * q[t_s] + a_s[:, None] * q[t_s + 1]
                rot_s, pos_s = self.fk.forward_once(qs)  # the frames' FK keeps its cache
                samples = self._sample_rows(len(q), smp, rot_s, pos_s, float(collision))
                if samples is not None and over(samples[0]):
                    return None, None
            col = self._exact_rows(q, col, samples, None if limit is None else limit - total)
            if col is None:
                return None, None
        if col is not None:
            res.append(col[0])
        res += [r for r, _ in extra]
        return np.concatenate(res, 1), lambda: self._jacobian(q, rot, pos, p_link, r_rot, col, extra)

    def _sample_rows(self, t: int, smp: tuple[np.ndarray, np.ndarray], rot: np.ndarray, pos: np.ndarray,
                     collision: float) -> tuple[np.ndarray, Callable] | None:
        """The proxies' rows at the samples between frames `sample_points` ((frame, α) arrays; FK
        (S,B,3,3), (S,B,3) at (1 − α)·q_t + α·q_t+1), split onto the two frames like MuJoCo's
        sample rows (`ExactContacts.rows`): √(1 − α)·r on frame t, √α·r on t+1, each with its
        frame's share of the Jacobian. Frame-local rows (T,K) and their Jacobian (T,K,n_ik) on
        demand, or None when no proxy pair is within the margin at any sample."""
        r, jac = self._collision(rot, pos, collision)
        # the hinge at `contact_sample_margin`, not the proxies' margin: w·relu(m − clearance)
        # is the proxies' row shifted down by w·(margin − m), with the same Jacobian where active
        shift = self.w_col * collision**0.5 * max(self.cfg.collision_margin - self.cfg.contact_sample_margin, 0.0)
        active = r > shift
        if not r.shape[1] or not active.any():
            return None
        # only the active (sample, row) entries, packed per frame like the proxies' own rows
        # (slot k = the frame's k-th entry): the samples' proxy block was (S·p) rows wide, ~96 %
        # of them zero, and the contact phase's JᵀJ paid for all of them
        act_s, act_c = np.nonzero(active)
        s_t, a = smp
        owner = np.concatenate([s_t[act_s], s_t[act_s] + 1])
        scale = np.concatenate([np.sqrt(1.0 - a[act_s]), np.sqrt(a[act_s])])
        src_s, src_c = np.tile(act_s, 2), np.tile(act_c, 2)
        order = np.argsort(owner, kind="stable")
        count = np.bincount(owner, minlength=t)
        slot = np.empty(len(owner), dtype=np.int64)
        slot[order] = np.arange(len(owner)) - (np.cumsum(count) - count)[owner[order]]
        out_r = np.zeros((t, int(count.max())))
        out_r[owner, slot] = scale * (r[src_s, src_c] - shift)

        def jacobian() -> np.ndarray:
            z, o = self.fk.joint_frames(rot, pos, list(self.ik))
            js = jac(z, o)
            out = np.zeros((t, out_r.shape[1], js.shape[2]))
            out[owner, slot] = scale[:, None] * js[src_s, src_c]
            return out

        return out_r, jacobian

    def _exact_rows(self, q: np.ndarray, col: tuple[np.ndarray, Callable],
                    samples: tuple[np.ndarray, Callable] | None = None,
                    limit: float | None = None) -> tuple[np.ndarray, Callable] | None:
        """The polish phase's collision rows: MuJoCo's contacts on the frames `exact.frames` picks,
        the proxies' rows on the others (and at `samples`, `_sample_rows`, when given). None when
        MuJoCo's rows alone pass `limit` (`ExactContacts.rows`)."""
        frames = self.exact.frames if self.exact.frames is not None else np.ones(len(q), dtype=bool)
        out = self.exact.rows(q, limit)
        if out is None:
            return None
        r_ex, j_ex = out
        if samples is not None:
            j_ex_now = j_ex
            r_ex, j_ex = np.concatenate([r_ex, samples[0]], 1), None
        r_px = np.where(frames[:, None], 0.0, col[0])
        # the proxies' block only as wide as the frames it stays on need: its rows are packed per
        # frame (slot k = the frame's k-th pair; an unused slot or a pair out of the margin is zero
        # with a zero Jacobian), and its widest frames are usually MuJoCo's, where it is zeroed
        used = np.flatnonzero(r_px.any(0))
        n_px = int(used[-1]) + 1 if len(used) else 0
        r_px = r_px[:, :n_px]

        def jacobian(z: np.ndarray, o: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
            """(T, P+E, J), written into `out` (zeros, that shape) when given: the proxies' block
            (zero on the exact frames), then MuJoCo's."""
            if out is None:
                out = np.zeros((len(q), n_px + r_ex.shape[1], z.shape[1]))
            if n_px == col[0].shape[1]:
                col[1](z, o, out[:, :n_px])
            else:
                out[:, :n_px] = col[1](z, o)[:, :n_px]
            out[:, :n_px][frames] = 0.0
            if samples is None:
                out[:, n_px:] = j_ex
            else:
                out[:, n_px: n_px + j_ex_now.shape[1]] = j_ex_now
                out[:, n_px + j_ex_now.shape[1]:] = samples[1]()
            return out

        return np.concatenate([r_px, r_ex], 1), jacobian

    def _jacobian(self, q: np.ndarray, rot: np.ndarray, pos: np.ndarray, p_link: np.ndarray,
                  r_rot: np.ndarray, col: tuple[np.ndarray, Callable] | None,
                  extra: list[tuple[np.ndarray, TermJacobian]] = ()) -> np.ndarray:
        z, o = self.fk.joint_frames(rot, pos, list(self.ik))  # (T,J,3) each

        lm = self.mask[:, self.link_body]  # (J,L)
        jp = point_jacobian(z, o, p_link[:, :4], lm[:, :4]) * self.w_pos[:, :, None, None]
        jr = (z[:, None] * lm[:, self.rot_cols].T[None, :, :, None]).transpose(0, 1, 3, 2)
        jr = jr * self.w_rot[:, :, None, None]
        # one array, each block written in place (the collision rows are most of it: no copies)
        n_col = col[0].shape[1] if col is not None else 0
        out = np.zeros((len(q), self.n_task_rows + n_col + sum(r.shape[1] for r, _ in extra), len(self.ik)))
        out[:, : jp.shape[1] * 3] = jp.reshape(len(q), -1, len(self.ik))
        out[:, jp.shape[1] * 3: self.n_task_rows] = jr.reshape(len(q), -1, len(self.ik))
        if col is not None:
            col[1](z, o, out[:, self.n_task_rows: self.n_task_rows + n_col])
        row = self.n_task_rows + n_col
        for r, jac in extra:
            out[:, row: row + r.shape[1]] = jac(z, o)
            row += r.shape[1]
        return out

    def _geometry(self, robot: Robot, link_bodies: list[str], backend: str,
                  term_bodies: list[str] = ()) -> dict[str, object]:
        """FK backend, joint masks and the proxy broad-phase tables (no targets involved).

        Sphere/hull pairs are grouped by (sphere body, hull) with a bounding sphere per sphere
        body: a cheap first broad phase, so per-point tests run only where a part is near a hull."""
        px = self.proxies
        proxy_bodies = px.bodies if px is not None else []
        fk = robot.fk(link_bodies + proxy_bodies + [b for b in term_bodies if b not in link_bodies], backend,
                      variable=list(self.ik))  # the other joints are fixed per solve (fingers, legs)
        out: dict[str, object] = {"fk": fk, "link_body": [fk.index[b] for b in link_bodies],
                                  "mask": fk.moves(list(self.ik))}  # mask (J, bodies)
        if px is None:
            return out
        sphere_body = np.array([fk.index[proxy_bodies[b]] for b in px.sphere_body], dtype=np.int64)
        hull_body = np.array([fk.index[proxy_bodies[b]] for b in px.hull_body], dtype=np.int64)
        s_body = sphere_body[px.hull_pairs[:, 0]]
        key = s_body * (len(px.hull_body) + 1) + px.hull_pairs[:, 1]
        _, inverse = np.unique(key, return_inverse=True)
        order = np.argsort(inverse, kind="stable")
        members = np.split(order, np.flatnonzero(np.diff(inverse[order])) + 1) if len(order) else []
        width = max((len(m) for m in members), default=1)
        first = np.array([m[0] for m in members], dtype=np.int64)
        part_body = np.unique(s_body)  # FK indices of bodies carrying paired spheres
        centre, radius = [], []
        for b in part_body:
            k = np.flatnonzero(sphere_body == b)
            c = px.centres[k].mean(0)
            centre.append(c)
            radius.append(float((np.linalg.norm(px.centres[k] - c, axis=1) + px.radii[k]).max()))
        out.update(
            sphere_body=sphere_body, hull_body=hull_body, part_body=part_body,
            group_members=np.array([np.concatenate([m, np.full(width - len(m), -1)]) for m in members],
                                   dtype=np.int64).reshape(-1, width),
            group_hull=px.hull_pairs[first, 1] if len(first) else first,
            group_part=np.searchsorted(part_body, s_body[first]) if len(first) else first,
            part_centre=np.array(centre).reshape(-1, 3), part_radius=np.array(radius),
            box_mid=px.hull_box.mean(1),
            hull_planes=[np.unique(p, axis=0) for p in px.hull_planes])  # unpadded plane sets
        out["plane_table"], out["plane_count"] = plane_table(out["hull_planes"])
        return out

    def _collision(self, rot: np.ndarray, pos: np.ndarray, scale: float = 1.0,
                   hulls: Callable[..., Contacts] | None = None) -> tuple[np.ndarray, Callable]:
        """Hinge residuals w·relu(margin − clearance) (T,P+Q) over the sphere/sphere and sphere/hull
        pairs within the margin somewhere, and a function of (axes, pivots) giving their Jacobian.
        `hulls`: the sphere/hull contact query (default the compiled `hull_contacts`; the tests
        pass `hull_contacts_numpy`, the reference)."""
        px, margin, w = self.proxies, self.cfg.collision_margin, self.w_col * scale**0.5
        t, n_ik = len(rot), len(self.ik)
        sb, hb = self.sphere_body, self.hull_body
        # sphere/sphere
        i, k = px.pairs[:, 0], px.pairs[:, 1]
        centres = pos[:, sb] + rotate(rot[:, sb], px.centres) if len(i) else np.zeros((t, 0, 3))
        diff = centres[:, i] - centres[:, k]
        dist = np.linalg.norm(diff, axis=-1)
        clear = dist - px.radii[i] - px.radii[k]
        near = np.flatnonzero((clear < margin).any(0))  # the other pairs contribute exactly zero
        i, k, diff, dist, clear = i[near], k[near], diff[:, near], dist[:, near], clear[:, near]
        gap = np.maximum(margin - clear, 0.0)
        # sphere/hull: the pairs within the margin, sorted by frame then pair (`proxy_hulls.py`)
        tc, qc, value, x, normal = (hulls or hull_contacts)(self.hulls, rot, pos, margin)
        si, hi = px.hull_pairs[:, 0], px.hull_pairs[:, 1]
        # rows packed per frame (slot k = the frame's k-th active pair): the cost is a sum of
        # squares per frame, so K = the most pairs active in one frame rows suffice, not one
        # column per pair active anywhere (a third of the Jacobian and JᵀJ work on G1)
        count = np.bincount(tc, minlength=t)
        col = np.arange(len(tc)) - (np.cumsum(count) - count)[tc]
        hgap = np.zeros((t, int(count.max()) if len(tc) else 0))
        hgap[tc, col] = margin - value

        def jacobian(z: np.ndarray, o: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
            """(T, P+K, J); written into `out` (zeros, that shape) when given."""
            if out is None:
                out = np.zeros((t, len(i) + hgap.shape[1], n_ik))
            ms = self.mask[:, sb]  # (J,N)
            if len(i):
                lever = lambda p: cross(z[:, None], p[:, :, None] - o[:, None])  # noqa: E731  (T,P,J,3)
                u = diff / np.maximum(dist, 1e-12)[..., None]
                dclear = (np.einsum("tpa,tpja->tpj", u, lever(centres[:, i])) * ms[:, i].T
                          - np.einsum("tpa,tpja->tpj", u, lever(centres[:, k])) * ms[:, k].T)
                out[:, : len(i)] = -w * (gap > 0)[..., None] * dclear
            moves = (ms[:, si[qc]] - self.mask[:, hb[hi[qc]]]).T  # (C,J)
            out[tc, len(i) + col] = -w * normal_jacobian(z, o, tc, x, normal) * moves
            return out

        return w * np.concatenate([gap, hgap], 1), jacobian
