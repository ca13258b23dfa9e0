"""Distance between two convex point hulls with its own bounds: the robot contact measure's check
on MuJoCo's `mj_geomDistance`.

MuJoCo 3.9-3.11's native CCD returns exactly 0.0 for some clearly separated convex mesh pairs
(google-deepmind/mujoco#3383; on G1 the Dex3 fingers against the other wrist, 2-6 cm apart, read
0.0), and its libccd fallback can return negative values for separated pairs. A 0.0 reads as a
touch, so the fidelity measure counted hands and faces centimetres apart as contacts. Here the
distance between conv(A) and conv(B) is computed on the Minkowski difference A − B (fully
corrective Frank-Wolfe, as GJK): every iterate x gives an upper bound |x| and a separating plane
with normal x, hence a lower bound; it stops when they agree to `tol`.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import nnls


def _min_norm(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The point of conv(points) (K,3) nearest the origin, and its convex weights (K,): the
    non-negative least-squares form min |Pᵀλ|² + (M(Σλ − 1))², λ ≥ 0, with M large."""
    big = 1e3
    a = np.vstack([points.T, np.full((1, len(points)), big)])
    lam, _ = nnls(a, np.r_[0.0, 0.0, 0.0, big])
    lam /= max(lam.sum(), 1e-300)
    return lam @ points, lam


def hull_distance(a: np.ndarray, b: np.ndarray, tol: float = 1e-4, iterations: int = 64
                  ) -> tuple[float, float]:
    """Lower and upper bound (m) of the distance between conv(a) and conv(b), (N,3) and (M,3)
    points; (0, ub ≤ `tol`) when they touch or overlap (no depth: see `geom_distance`).

    Fully corrective Frank-Wolfe (GJK's idea): the support point of A − B towards −x joins an
    active set, x becomes the exact nearest point of that set's hull (`_min_norm`), and points
    of zero weight leave it. |x| is an upper bound; the support plane with normal x a lower one."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    x = a.mean(0) - b.mean(0)
    active = x[None]
    lower = 0.0
    for _ in range(iterations):
        n = float(np.linalg.norm(x))
        if n <= tol:
            return 0.0, n
        s = a[(a @ -x).argmax()] - b[(b @ x).argmax()]  # support of A − B towards −x
        lower = max(lower, float(s @ x) / n)  # every point of A − B lies beyond this plane
        if n - lower <= tol:
            return lower, n
        x, lam = _min_norm(np.vstack([active, s]))
        active = np.vstack([active, s])[lam > 1e-12]
    return lower, float(np.linalg.norm(x))


def geom_points(model, data, g: int) -> np.ndarray:
    """World-frame points whose hull is geom `g` (mesh: its vertices; box: its corners)."""
    import mujoco

    pos, rot = data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3)
    if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
        m = model.geom_dataid[g]
        v = model.mesh_vert[model.mesh_vertadr[m]: model.mesh_vertadr[m] + model.mesh_vertnum[m]]
    elif model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
        v = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T * model.geom_size[g]
    else:
        raise ValueError(f"geom {g}: type {model.geom_type[g]} has no point hull here")
    return np.asarray(v, dtype=np.float64) @ rot.T + pos


def geom_distance(model, data, ga: int, gb: int, distmax: float, fromto: np.ndarray) -> float:
    """`mj_geomDistance`, checked where it claims a touch: a reading ≤ 0 is recomputed by
    `hull_distance`; when that finds the hulls apart its distance replaces MuJoCo's, when it
    finds them touching MuJoCo's (penetration depth) stands. Positive readings are kept (they
    agree with `hull_distance` to < 0.5 mm on G1, tested)."""
    import mujoco

    d = float(mujoco.mj_geomDistance(model, data, ga, gb, distmax, fromto))
    if d > 0.0:
        return d
    hulls = (mujoco.mjtGeom.mjGEOM_MESH, mujoco.mjtGeom.mjGEOM_BOX)
    if not all(model.geom_type[g] in hulls for g in (ga, gb)):
        return d  # a sphere or capsule (H1's hands): MuJoCo's own primitive distance is exact
    lower, upper = hull_distance(geom_points(model, data, ga), geom_points(model, data, gb))
    if lower > 0.0:
        return min(0.5 * (lower + upper), distmax)
    return d
