"""`fidelity`: how sign fidelity (location, orientation, handshape, movement, contact) is measured."""

from __future__ import annotations

from pydantic import Field

from embody.config.base import Section


class FidelityConfig(Section):
    #: A hand is "at" a landmark when its palm is within this many body scales (shoulder widths)
    #: of it: the frames that location agreement counts.
    location_radius: float = Field(0.5, gt=0.0, le=5.0)
    #: Surfaces closer than this (m) are in contact (hand-hand, hand-face, hand-chest).
    contact_eps: float = Field(0.015, gt=0.0, le=0.2)
    #: The robot touches when its geoms are this close (m). None (default): the human's ε at
    #: hand scale, ε × robot/human hand length (wrist → middle tip; G1 Dex3 1.42 → 2.1 cm;
    #: `embody.metrics.fidelity.robot_contact_eps`). A contact is a gap small against the hands
    #: making it; the IK keeps the robot's non-touching hand gaps at the same hand scale
    #: (`ik.w_hand_clearance`), so a human gap just over ε maps to a robot gap just over this.
    #: Its touches stop at the collision margin (MuJoCo: 1.3-1.7 cm), which a fixed 1.5 cm split.
    robot_contact_eps: float | None = Field(None, gt=0.0, le=0.2)
    #: Location agreement accepts ties: the robot's nearest landmark agrees when a palm is
    #: within this many body scales as near to it as to the human's (face landmarks lie
    #: 1.5-4 cm apart; the human's own 1st and 2nd nearest differ by a median 1.4 cm at the face).
    location_tie: float = Field(0.05, ge=0.0, le=0.5)
    #: A robot contact deeper than this (m) is a penetration, and does not count as a contact.
    penetration_tol: float = Field(0.002, ge=0.0, le=0.05)
    #: With location-preserving targets, also solve the plain shape-fit IK in the metrics step,
    #: so Table III compares both (costs one more IK solve per sequence).
    baseline: bool = True
