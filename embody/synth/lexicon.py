"""A small made-up sign lexicon: enough variety of place, handshape, movement and two-handedness
to exercise the pipeline the way real signing does."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Movement = Literal["hold", "tap", "line", "circle", "repeat"]
#: one-handed; both hands mirrored; the dominant hand acting on a static base hand; hands meeting.
Hands = Literal["one", "mirror", "base", "contact"]


@dataclass(frozen=True)
class Sign:
    gloss: str
    location: str
    handshape: str
    movement: Movement
    hands: Hands = "one"
    #: handshape of the non-dominant hand in two-handed signs.
    base_shape: str = "flat"


LEXICON: tuple[Sign, ...] = (
    Sign("HELLO", "forehead", "flat", "line"),
    Sign("THANK-YOU", "chin", "flat", "line"),
    Sign("NAME", "neutral", "v", "tap", "base", "v"),
    Sign("WHAT", "neutral", "spread", "repeat", "mirror", "spread"),
    Sign("HOUSE", "neutral_high", "flat", "line", "mirror", "flat"),
    Sign("WANT", "neutral", "claw", "line", "mirror", "claw"),
    Sign("I", "chest", "point", "tap"),
    Sign("YOU", "center", "point", "hold"),
    Sign("THINK", "forehead", "point", "tap"),
    Sign("GOOD", "chin", "flat", "line", "base", "flat"),
    Sign("MEET", "center", "point", "line", "contact", "point"),
    Sign("FRIEND", "center", "c", "repeat", "contact", "c"),
    Sign("WORK", "neutral", "fist", "tap", "base", "fist"),
    Sign("PLAY", "neutral", "y", "repeat", "mirror", "y"),
    Sign("WATER", "chin", "pinch", "tap"),
    Sign("MOTHER", "cheek", "spread", "tap"),
    Sign("MY", "chest", "flat", "hold"),
    Sign("BIG", "neutral", "c", "line", "mirror", "c"),
    Sign("WHERE", "side", "point", "repeat"),
    Sign("SCHOOL", "neutral", "flat", "tap", "contact", "flat"),
    Sign("LEARN", "forehead", "pinch", "line", "base", "flat"),
    Sign("FINISH", "neutral_high", "spread", "circle", "mirror", "spread"),
    Sign("SORRY", "chest", "fist", "circle"),
    Sign("HELP", "neutral_low", "fist", "line", "base", "flat"),
    Sign("SHOULDER", "opposite_shoulder", "flat", "tap"),
)
