"""Reusable metrics shared by the retargeting and critic stages."""

from embody.metrics.trajectory import (
    dtw_distance,
    jerk,
    mean_jerk,
    position_error,
    rotation_error_deg,
)

__all__ = ["dtw_distance", "jerk", "mean_jerk", "position_error", "rotation_error_deg"]
