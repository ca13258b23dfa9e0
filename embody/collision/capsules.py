"""Limb core capsules: a separation term for limbs that pass through each other.

The point energy (`energy`) pushes each penetrating point to the nearest face of the piece it is
in. When a forearm has passed right through the other (their axes cross, as in the synthetic
set's crossed-hands artifact), the points on either side of the crossing push in opposite
directions and cancel: the optimiser sits at a saddle with the forearms ~5 cm deep (measured
on seq_000: axes 1-2 mm apart over 20 frames, point energy stuck for 400 steps).

Each arm segment (upper arm, forearm, palm) gets a *core* capsule along its bone, thinner
than the skin (`CORE` × a low percentile of its vertices' distance to the bone), so two cores
overlapping implies the skins overlap: the term never moves a clear frame. Its gradient moves
the two bones apart along one direction (their closest points' offset), which the point energy
cannot, and once the cores are apart the point energy removes the rest.
"""

from __future__ import annotations

import weakref
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from numba import njit

from embody.body.base import BodyModel
from embody.collision.exclusions import checked_pairs, part_groups

#: (part, bone start joint, bone end joint) of each arm segment, per side.
SEGMENTS = (("{s}_shoulder", "{s}_shoulder", "{s}_elbow"),
            ("{s}_elbow", "{s}_elbow", "{s}_wrist"),
            ("{s}_wrist", "{s}_wrist", "{s}_middle1"))
#: Core radius as a fraction of the segment's 10th-percentile skin radius.
CORE = 0.8


@dataclass(frozen=True)
class Capsules:
    """Bone joints (P,2) of both segments of each checked cross-arm pair and their summed core
    radii (P,)."""

    a: np.ndarray
    b: np.ndarray
    reach: np.ndarray


_cache: weakref.WeakKeyDictionary[BodyModel, dict[tuple, Capsules]] = weakref.WeakKeyDictionary()


def _radius(rest: np.ndarray, p: np.ndarray, q: np.ndarray) -> float:
    """10th percentile distance to the bone pq of the vertices projecting inside its middle."""
    d = q - p
    t = ((rest - p) @ d) / float(d @ d)
    mid = rest[(t > 0.15) & (t < 0.85)]
    if len(mid) == 0:
        return 0.0
    dist = np.linalg.norm(mid - (p + np.outer(((mid - p) @ d) / float(d @ d), d)), axis=1)
    return float(np.percentile(dist, 10))


def arm_capsules(body: BodyModel, betas: np.ndarray,
                 allow_pairs: Iterable[Sequence[str]] = ()) -> Capsules:
    """The cross-arm core capsule pairs of a body shape, skipping allowed group pairs (cached)."""
    allow = tuple(tuple(p) for p in allow_pairs)
    key = (np.asarray(betas, dtype=np.float64).round(6).tobytes(), allow)
    cache = _cache.setdefault(body, {})
    if key in cache:
        return cache[key]
    names = list(body.joint_names)
    b = torch.as_tensor(np.asarray(betas, dtype=np.float64))
    with torch.no_grad():
        rest = body.rest_vertices(b).double().numpy()
        joints = body.joint_transforms(torch.zeros(1, 55, 3, dtype=torch.float64),
                                       b)[0, :, :3, 3].numpy()
    groups, part_group = part_groups(body.part_names)
    checked = checked_pairs(groups, body.joint_names, body.parents, allow)
    vparts = np.asarray(body.vertex_parts)
    segs = {}
    for side in ("left", "right"):
        for part, j0, j1 in SEGMENTS:
            part, j0, j1 = part.format(s=side), j0.format(s=side), j1.format(s=side)
            if part not in body.part_names or j0 not in names or j1 not in names:
                continue
            pi = list(body.part_names).index(part)
            i0, i1 = names.index(j0), names.index(j1)
            r = CORE * _radius(rest[vparts == pi], joints[i0], joints[i1])
            segs[(side, part)] = (i0, i1, r, int(part_group[pi]))
    a, bb, reach = [], [], []
    for (sa, _), (a0, a1, ra, ga) in segs.items():
        for (sb, _), (b0, b1, rb, gb) in segs.items():
            if sa == "left" and sb == "right" and checked[ga, gb] and ra > 0 and rb > 0:
                a.append((a0, a1))
                bb.append((b0, b1))
                reach.append(ra + rb)
    out = Capsules(np.array(a, dtype=np.int64).reshape(-1, 2),
                   np.array(bb, dtype=np.int64).reshape(-1, 2), np.array(reach))
    cache[key] = out
    return out


def segment_distance(p1: torch.Tensor, q1: torch.Tensor, p2: torch.Tensor,
                     q2: torch.Tensor) -> torch.Tensor:
    """Distance (...) between segments p1q1 and p2q2 (...,3) (Ericson 5.1.9), differentiable."""
    _, _, a, b = segment_closest(p1, q1, p2, q2)
    return ((a - b).square().sum(-1) + 1e-12).sqrt()


def segment_closest(p1: torch.Tensor, q1: torch.Tensor, p2: torch.Tensor, q2: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Closest points of segments p1q1 and p2q2: parameters s, t (...) and points (...,3)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e = (d1 * d1).sum(-1), (d2 * d2).sum(-1)
    f, c, b = (d2 * r).sum(-1), (d1 * r).sum(-1), (d1 * d2).sum(-1)
    denom = a * e - b * b
    s = torch.where(denom > 1e-12, ((b * f - c * e) / denom.clamp(min=1e-12)).clamp(0, 1),
                    torch.zeros_like(a))
    t = (b * s + f) / e
    s = torch.where(t < 0, (-c / a).clamp(0, 1), torch.where(t > 1, ((b - c) / a).clamp(0, 1), s))
    t = t.clamp(0, 1)
    return s, t, p1 + d1 * s.unsqueeze(-1), p2 + d2 * t.unsqueeze(-1)


def capsule_overlaps(caps: Capsules, transforms: torch.Tensor, margin: float = 0.0) -> torch.Tensor:
    """Per frame and pair max(0, r_a + r_b + margin − d) (T,P) from joint transforms (T,J,4,4)."""
    p = transforms[:, :, :3, 3]
    d = segment_distance(p[:, caps.a[:, 0]], p[:, caps.a[:, 1]], p[:, caps.b[:, 0]],
                         p[:, caps.b[:, 1]])
    return torch.relu(torch.as_tensor(caps.reach, dtype=p.dtype, device=p.device) + margin - d)


def capsule_energies(caps: Capsules, transforms: torch.Tensor, margin: float = 0.0,
                     compiled: bool = False) -> torch.Tensor:
    """Per-frame Σ_pairs max(0, r_a + r_b + margin − d)² (T,) from joint transforms (T,J,4,4).
    `compiled` (CPU): one compiled pass with a hand-written gradient (`CapsuleEnergies`)."""
    if len(caps.reach) == 0:
        return transforms.new_zeros(transforms.shape[0]) + 0.0 * transforms[:, 0, 0, 0]
    if compiled and transforms.device.type == "cpu":
        return CapsuleEnergies.apply(transforms, caps, margin)
    over = capsule_overlaps(caps, transforms, margin)
    return (over * over).sum(-1)


@njit(cache=True, nogil=True)
def _closest(pos: np.ndarray, i1: int, j1: int, i2: int, j2: int,
             out: np.ndarray) -> tuple[float, float]:
    """`segment_closest` of segments pos[i1]pos[j1] and pos[i2]pos[j2] in float64 (same
    branches): (s, t), and out = c1 − c2."""
    a = e = f = c = b = 0.0
    for k in range(3):
        d1, d2, r = pos[j1, k] - pos[i1, k], pos[j2, k] - pos[i2, k], pos[i1, k] - pos[i2, k]
        a += d1 * d1
        e += d2 * d2
        f += d2 * r
        c += d1 * r
        b += d1 * d2
    denom = a * e - b * b
    s = min(max((b * f - c * e) / max(denom, 1e-12), 0.0), 1.0) if denom > 1e-12 else 0.0
    t = (b * s + f) / e
    if t < 0:
        s = min(max(-c / a, 0.0), 1.0)
    elif t > 1:
        s = min(max((b - c) / a, 0.0), 1.0)
    t = min(max(t, 0.0), 1.0)
    for k in range(3):
        out[k] = (pos[i1, k] + (pos[j1, k] - pos[i1, k]) * s) \
            - (pos[i2, k] + (pos[j2, k] - pos[i2, k]) * t)
    return s, t


@njit(cache=True, nogil=True)
def _capsule_pass(pos: np.ndarray, a: np.ndarray, b: np.ndarray, reach: np.ndarray,
                  margin: float, grad: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Per-frame energies (T,); with `grad` (T,) non-empty, ∂(Σ grad·E)/∂pos into `out`
    (T,J,3). The distance's gradient is the closest points' unit offset, shared between each
    segment's ends by (1 − s, s) and (1 − t, t): s, t minimise the distance (or sit at a bound),
    so their own derivatives do not enter (envelope theorem; what autograd through
    `segment_closest` gives, to rounding)."""
    n_t = pos.shape[0]
    e = np.zeros(n_t)
    diff = np.empty(3)
    backward = len(grad) > 0
    for t in range(n_t):
        for i in range(len(reach)):
            s, u = _closest(pos[t], a[i, 0], a[i, 1], b[i, 0], b[i, 1], diff)
            d = np.sqrt(diff[0] * diff[0] + diff[1] * diff[1] + diff[2] * diff[2] + 1e-12)
            over = reach[i] + margin - d
            if over <= 0.0:
                continue
            e[t] += over * over
            if backward and grad[t] != 0.0:
                g = -2.0 * over * grad[t] / d  # ∂/∂(c1 − c2) = g·(c1 − c2)
                for k in range(3):
                    gk = g * diff[k]
                    out[t, a[i, 0], k] += (1.0 - s) * gk
                    out[t, a[i, 1], k] += s * gk
                    out[t, b[i, 0], k] -= (1.0 - u) * gk
                    out[t, b[i, 1], k] -= u * gk
    return e


class CapsuleEnergies(torch.autograd.Function):
    """`capsule_energies` as one compiled forward and a hand-written backward (CPU, float64
    inside). Why: its ~40 small tensor ops and their autograd nodes were ~10 % of an Adam
    step of the collision optimiser, for a handful of capsule pairs."""

    @staticmethod
    def forward(ctx, transforms: torch.Tensor, caps: Capsules, margin: float) -> torch.Tensor:
        pos = transforms.detach()[:, :, :3, 3].double().contiguous().numpy()
        ctx.pos, ctx.caps, ctx.margin = pos, caps, margin
        ctx.shape = transforms.shape
        e = _capsule_pass(pos, caps.a, caps.b, caps.reach, margin, np.empty(0),
                          np.empty((0, 0, 3)))
        return torch.from_numpy(e).to(transforms.dtype)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        g_pos = np.zeros(ctx.pos.shape)
        c = ctx.caps
        _capsule_pass(ctx.pos, c.a, c.b, c.reach, ctx.margin,
                      grad.detach().double().contiguous().numpy(), g_pos)
        out = torch.zeros(ctx.shape, dtype=grad.dtype)
        out[:, :, :3, 3] = torch.from_numpy(g_pos)
        return out, None, None
