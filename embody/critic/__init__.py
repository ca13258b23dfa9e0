"""Critics and the refinement loop: control primitives, a geometric and a VLM critic."""

from embody.critic.action import ACTION_SCHEMA, Action, Limits
from embody.critic.base import Critic, CritiqueContext
from embody.critic.geometric import GeometricCritic
from embody.critic.primitives import ORIENTATION_NAMES, POSITION_NAMES, Primitive, apply_primitives
from embody.critic.refine import RefineResult, RoundRecord, make_critic, refine, refine_table
from embody.critic.vlm import VLMClient, VLMCritic, VLMError

__all__ = ["ACTION_SCHEMA", "Action", "Critic", "CritiqueContext", "GeometricCritic", "Limits",
           "ORIENTATION_NAMES", "POSITION_NAMES", "Primitive", "RefineResult", "RoundRecord",
           "VLMClient", "VLMCritic", "VLMError", "apply_primitives", "make_critic", "refine",
           "refine_table"]
