"""The critic's action: the paper's JSON form, its schema, and a parser that never raises.

The same schema dict validates replies and is sent as the VLM's `response_format`, so a server
that enforces it (vLLM, llama.cpp grammars) cannot produce an unknown primitive in the first place.
Anything that still fails (malformed JSON, unknown names, bad amounts or windows) becomes an
invalid action with the reason recorded: the loop treats it as "no action" and goes on.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from typing import Any, Literal

import jsonschema

from embody.critic.primitives import ORIENTATION_NAMES, POSITION_NAMES, Primitive

log = logging.getLogger(__name__)

Verdict = Literal["accept", "revise"]


def _item_schema(names: tuple[str, ...]) -> dict[str, Any]:
    return {"anyOf": [
        {"type": "string", "enum": list(names)},
        {"type": "object", "additionalProperties": False,
         "required": ["name", "amount", "window"],
         "properties": {
             "name": {"type": "string", "enum": list(names)},
             "amount": {"type": ["number", "null"]},
             "window": {"anyOf": [{"type": "null"},
                                  {"type": "array", "items": {"type": "integer"}}]},
         }},
    ]}


#: JSON schema of an action; strict-mode compatible (every key required, no extra keys).
ACTION_SCHEMA: dict[str, Any] = {
    "type": "object",
    "additionalProperties": False,
    "required": ["primitives_positions", "primitives_orientation", "verdict", "reason"],
    "properties": {
        "primitives_positions": {"type": "array", "items": _item_schema(POSITION_NAMES)},
        "primitives_orientation": {"type": "array", "items": _item_schema(ORIENTATION_NAMES)},
        "verdict": {"type": "string", "enum": ["accept", "revise"]},
        "reason": {"type": "string"},
    },
}


@dataclass(frozen=True)
class Limits:
    """What a valid action may ask for: frame count, default and largest amounts."""

    num_frames: int
    position_step_m: float = 0.10
    angle_step_deg: float = 20.0
    max_position_m: float = 0.30
    max_angle_deg: float = 60.0


@dataclass(frozen=True)
class Action:
    """A critique result. `valid` is false when the reply was rejected (then it is a no-op)."""

    primitives: tuple[Primitive, ...] = ()
    verdict: Verdict = "revise"
    reason: str = ""
    valid: bool = True
    error: str | None = None
    raw: str | None = field(default=None, compare=False)

    @property
    def accepted(self) -> bool:
        return self.valid and self.verdict == "accept"

    @classmethod
    def rejected(cls, error: str, raw: str | None = None) -> "Action":
        log.warning("critic action rejected: %s", error)
        return cls(verdict="revise", reason="", valid=False, error=error, raw=raw)

    def to_json(self) -> dict[str, Any]:
        """The paper's form, items as objects; plus `valid`/`error` for the record."""
        return {
            "primitives_positions": [p.to_json() for p in self.primitives if p.kind == "position"],
            "primitives_orientation": [p.to_json() for p in self.primitives
                                       if p.kind == "orientation"],
            "verdict": self.verdict, "reason": self.reason, "valid": self.valid,
            "error": self.error,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> "Action":
        """Inverse of `to_json` (for stored records; no validation)."""
        prims = tuple(
            Primitive(p["name"], float(p["amount"]),
                      tuple(p["window"]) if p.get("window") is not None else None)  # type: ignore[arg-type]
            for key in ("primitives_positions", "primitives_orientation") for p in data[key])
        return cls(prims, data["verdict"], data.get("reason", ""), data.get("valid", True),
                   data.get("error"))

    @classmethod
    def parse(cls, reply: str | dict[str, Any], limits: Limits) -> "Action":
        """Validate a critic reply (JSON text or dict); never raises."""
        raw = reply if isinstance(reply, str) else None
        if isinstance(reply, str):
            try:
                reply = json.loads(_strip_fences(reply))
            except json.JSONDecodeError as exc:
                return cls.rejected(f"malformed JSON: {exc.msg} at char {exc.pos}", raw)
        try:
            jsonschema.validate(reply, ACTION_SCHEMA)
        except jsonschema.ValidationError as exc:
            where = "/".join(str(p) for p in exc.absolute_path) or "<root>"
            return cls.rejected(f"schema violation at {where}: {exc.message[:200]}", raw)
        prims: list[Primitive] = []
        for key, default, largest in (
                ("primitives_positions", limits.position_step_m, limits.max_position_m),
                ("primitives_orientation", limits.angle_step_deg, limits.max_angle_deg)):
            for item in reply[key]:
                item = {"name": item, "amount": None, "window": None} if isinstance(item, str) else item
                amount = default if item["amount"] is None else float(item["amount"])
                if not (math.isfinite(amount) and 0.0 < amount <= largest):
                    return cls.rejected(f"{item['name']}: amount {amount} outside (0, {largest}]", raw)
                window = item["window"]
                if window is not None:
                    if len(window) != 2 or window[0] > window[1]:
                        return cls.rejected(f"{item['name']}: window must be [start, end] with "
                                            f"start <= end, got {window}", raw)
                    if window[1] < 0 or window[0] >= limits.num_frames:
                        return cls.rejected(f"{item['name']}: window {window} outside frames "
                                            f"0..{limits.num_frames - 1}", raw)
                    window = (max(0, window[0]), min(limits.num_frames - 1, window[1]))
                prims.append(Primitive(item["name"], amount, window))
        return cls(tuple(prims), reply["verdict"], reply["reason"], raw=raw)


def _strip_fences(text: str) -> str:
    """Models without schema support wrap JSON in ```json fences; take what is inside."""
    text = text.strip()
    if text.startswith("```"):
        text = text.split("\n", 1)[1] if "\n" in text else ""
        text = text.rsplit("```", 1)[0]
    return text
