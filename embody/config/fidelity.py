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
    #: The robot touches when its geoms are this close (m): contact_eps plus the IK's 15 mm
    #: collision margin, which the robot keeps on purpose (touch without penetration).
    robot_contact_eps: float = Field(0.03, gt=0.0, le=0.2)
    #: A robot contact deeper than this (m) is a penetration, and does not count as a contact.
    penetration_tol: float = Field(0.002, ge=0.0, le=0.05)
    #: With location-preserving targets, also solve the plain shape-fit IK in the metrics step,
    #: so Table III compares both (costs one more IK solve per sequence).
    baseline: bool = True
