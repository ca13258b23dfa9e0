"""Collision mitigation in SMPL-X space: volumetric self-collision energy and masked optimisation.

`mitigate(motion, body, cfg)` is the stage API; `collision_energy` / `frame_collision_energies`
score a motion; `metrics.table1/table2` reproduce the paper's tables.
"""

from embody.collision.energy import CollisionModel, collision_model, energy, frame_energies
from embody.collision.masks import PRESETS, mask_joints
from embody.collision.optimize import (CollisionResult, collision_energy,
                                       frame_collision_energies, mitigate)
from embody.collision.volumes import PartVolumes, overfill_report, part_volumes

__all__ = ["PRESETS", "CollisionModel", "CollisionResult", "PartVolumes", "collision_energy",
           "collision_model", "energy", "frame_collision_energies", "frame_energies",
           "mask_joints", "mitigate", "overfill_report", "part_volumes"]
