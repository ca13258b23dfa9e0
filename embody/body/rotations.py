"""Axis-angle → rotation matrix in torch, smooth at zero so rest-pose gradients stay finite."""

from __future__ import annotations

import torch

#: Below this squared angle the Taylor series is exact to float64 precision.
_SMALL = 1e-6


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula for (..., 3) → (..., 3, 3), keeping dtype and device.

    Uses R = I + a K + b (r rᵀ − θ² I) with a = sin θ/θ and b = (1 − cos θ)/θ², written with
    θ² and a series near zero: the plain `norm` form has a NaN gradient at the T-pose.
    """
    r = axis_angle
    theta2 = (r * r).sum(-1)
    small = theta2 < _SMALL
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe2)
    half_sin = torch.sin(0.5 * theta)
    a = torch.where(small, 1.0 - theta2 / 6.0 + theta2 * theta2 / 120.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0 + theta2 * theta2 / 720.0, 2.0 * half_sin * half_sin / safe2)
    x, y, z = r.unbind(-1)
    zero = torch.zeros_like(x)
    skew = torch.stack((zero, -z, y, z, zero, -x, -y, x, zero), -1).reshape(*r.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    outer = r[..., :, None] * r[..., None, :]
    return (eye * (1.0 - b * theta2)[..., None, None] + a[..., None, None] * skew
            + b[..., None, None] * outer)
