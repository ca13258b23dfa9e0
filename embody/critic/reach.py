"""What the robot can reach: the part of a requested palm move that its clearances allow.

Why: the critic's location offsets scale the human palm's offset from its nearest landmark by the
body-scale ratio (G1: 0.76 of the human), but the IK keeps the robot's hand off its chest by the
human's hand-chest gap at *hand* scale (min(ρ·g, `ik.hand_gap_max`), ρ = 1.42 on G1:
`embody.retarget.hand_clearance`) and off its face by the collision margin or, where the human's
hand is apart from the face, by its gap at hand scale up to 2.5 cm (`targets.FACE_GAP_MAX`), and a Dex3 palm
centre sits deeper inside a thicker hand. So where the human's hand is a few centimetres before
the chest, or touches the face, the robot palm sits 2-4 cm further forward than the rescaled
human's while its hand already stands at its clearance: the critic asked for "back" moves the
next IK round could not honour, and rejected every round for the same reason (default G1 run,
2026-11-26: 14 of 24 rejected, the rounds lowering the windowed offset by ~10 % each).

So per frame and hand, the component of the move toward the face or the chest (along MuJoCo's
closest-point direction between the hand's and the surface's geoms) is limited to the room the
hand has there: its distance minus the clearance the IK keeps (minus `critic.reach_slack_m`).
The critic still asks for moves along the surface (up, down, in, out), away from it, and toward it
as far as the clearance allows, and judges acceptance on that: the location error the robot can
still reduce.
"""

from __future__ import annotations

import mujoco
import numpy as np

from embody.metrics.embodiments import RobotContactGeoms, closest_pair
from embody.robot import Robot

SIDES = ("left", "right")
#: Surfaces a hand is held off, in the order of `required`'s last axis.
SURFACES = ("face", "chest")


class Reach:
    """Closest hand-surface distances and directions of one robot, and the clamp they imply."""

    def __init__(self, robot: Robot, distmax: float = 0.1) -> None:
        self.robot = robot
        self.geoms = RobotContactGeoms(robot)
        self.distmax = float(distmax)
        self.rot = np.asarray(robot.torso_from_world)[:3, :3]  # world → the targets' torso frame

    def closest(self, q: np.ndarray, frames: np.ndarray, side: str
                ) -> tuple[np.ndarray, np.ndarray]:
        """Per frame in `frames` and surface: distance (F,2) (m; `distmax` when farther) and unit
        direction hand → surface (F,2,3) in the torso frame (0 where unknown: touching or far)."""
        m, d = self.robot.model, mujoco.MjData(self.robot.model)
        dist = np.full((len(frames), len(SURFACES)), self.distmax)
        direction = np.zeros((len(frames), len(SURFACES), 3))
        hand = self.geoms.sets[f"{side}_hand"]
        for i, t in enumerate(frames):
            d.qpos[:] = self.robot.qpos(q[t])
            mujoco.mj_kinematics(m, d)
            for j, surface in enumerate(SURFACES):
                dist[i, j], fromto = closest_pair(m, d, hand, self.geoms.sets[surface], self.distmax)
                v = fromto[3:] - fromto[:3]
                n = np.linalg.norm(v)
                if dist[i, j] > 1e-4 and n > 1e-9:
                    direction[i, j] = self.rot @ v / n
        return dist, direction

    def clamp(self, q: np.ndarray, offset: np.ndarray, required: np.ndarray, slack: float,
              fallback: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`offset` (T,2,3) with its approach to each surface limited to the room the hand has
        there: its distance minus the clearance the IK keeps, minus `slack`.

        `required` (T,2,2): per frame, hand and surface the clearance the IK keeps (m);
        `fallback` (T,2,3): the direction toward the surface where MuJoCo gives none (touching).
        Returns the reachable offset and the per-frame, per-hand blocked mask (T,2)."""
        out = np.array(offset, dtype=np.float64)
        blocked = np.zeros(out.shape[:2], dtype=bool)
        for s, side in enumerate(SIDES):
            frames = np.flatnonzero(np.linalg.norm(out[:, s], axis=-1) > 0)
            if not len(frames):
                continue
            dist, direction = self.closest(q, frames, side)
            for j in range(len(SURFACES)):
                n = np.where((np.linalg.norm(direction[:, j], axis=-1) > 0)[:, None],
                             direction[:, j], fallback[frames, s])
                move = out[frames, s]
                room = np.maximum(dist[:, j] - required[frames, s, j] - slack, 0.0)
                excess = np.maximum((move * n).sum(-1) - room, 0.0)
                out[frames, s] = move - excess[:, None] * n
                blocked[frames, s] |= excess > 0
        return out, blocked
