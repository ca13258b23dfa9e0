import numpy as np
import pytest

from embody.metrics.trajectory import dtw_distance, jerk, mean_jerk, position_error, rotation_error_deg


def _rotz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_position_error_is_euclidean():
    a = np.zeros((4, 2, 3))
    b = np.zeros((4, 2, 3))
    b[..., 0] = 3.0
    b[..., 1] = 4.0
    assert np.allclose(position_error(a, b), 5.0)


def test_rotation_error_degrees():
    angles = np.radians([0.0, 10.0, 90.0, 180.0])
    ra = np.stack([np.eye(3)] * 4)
    rb = np.stack([_rotz(a) for a in angles])
    assert np.allclose(rotation_error_deg(ra, rb), [0.0, 10.0, 90.0, 180.0], atol=1e-5)


def test_dtw_ignores_time_warping():
    t = np.linspace(0, 1, 40)
    a = np.stack([np.sin(2 * np.pi * t), t, np.zeros_like(t)], axis=1)
    slow = np.repeat(a, 2, axis=0)  # same path at half speed
    assert dtw_distance(a, slow) == pytest.approx(0.0, abs=1e-12)
    lifted = a + np.array([0.0, 0.0, 0.1])  # offset orthogonal to the path: no warp helps
    assert dtw_distance(a, lifted) == pytest.approx(0.1, rel=1e-9)
    with pytest.raises(ValueError):
        dtw_distance(a, np.zeros((5, 2)))


def test_jerk_of_polynomials():
    fps = 50.0
    t = np.arange(20) / fps
    assert np.allclose(jerk(t**2, fps), 0.0, atol=1e-6)  # quadratic: zero jerk
    assert np.allclose(jerk(t**3, fps), 6.0, atol=1e-6)  # cubic: constant jerk 6
    assert mean_jerk(np.zeros(3), fps) == 0.0


def _dtw_cell_loop(a, b):
    """The textbook O(Ta·Tb) cell loop (ties: diagonal, up, left), as the reference."""
    a, b = np.asarray(a, float).reshape(len(a), -1), np.asarray(b, float).reshape(len(b), -1)
    cost = np.sqrt(((a[:, None] - b[None]) ** 2).sum(-1))
    acc = np.full((len(a) + 1, len(b) + 1), np.inf)
    steps = np.zeros_like(acc)
    acc[0, 0] = 0.0
    for i in range(1, len(a) + 1):
        for j in range(1, len(b) + 1):
            choices = (acc[i - 1, j - 1], acc[i - 1, j], acc[i, j - 1])
            k = int(np.argmin(choices))
            acc[i, j] = cost[i - 1, j - 1] + choices[k]
            steps[i, j] = steps[((i - 1, j - 1), (i - 1, j), (i, j - 1))[k]] + 1
    return acc[-1, -1], acc[-1, -1] / steps[-1, -1]


def test_dtw_matches_the_cell_loop_including_ties():
    """Bit for bit: the compiled recursion (`metrics.warping`) makes the loop's choices and sums."""
    rng = np.random.default_rng(3)
    cases = [(rng.normal(size=(23, 2, 3)), rng.normal(size=(31, 2, 3))),
             (rng.integers(0, 2, (17, 2)).astype(float), rng.integers(0, 2, (9, 2)).astype(float)),
             (rng.normal(size=(1, 3)), rng.normal(size=(6, 3))),
             (rng.normal(size=(150, 2, 3)), rng.normal(size=(301, 2, 3)))]
    for a, b in cases:
        total, normalised = _dtw_cell_loop(a, b)
        assert dtw_distance(a, b, normalise=False) == total
        assert dtw_distance(a, b) == normalised
