"""Which part pairs the energy checks: collision groups and the excluded-pair matrix.

Pieces move with their own joint, but collisions are counted between *groups*: each hand (wrist
plus its 15 finger segments) is one group, like VolumetricSMPL's split, and every other part is
its own group. A pair of groups is excluded when it is:

* parent–child in the part tree (a joint without vertices, e.g. the mannequin's collars, passes
  its children to its own parent group: upper arm–chest at the shoulder);
* listed in `ALWAYS_TOUCHING` below (anatomical contact in ordinary poses);
* allowed on purpose by the config (`allow_pairs`, e.g. a sign touching the chin).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from embody.body.parts import default_merge
from embody.errors import ConfigError

#: Anatomically always-touching pairs (absent groups are ignored, so one list serves both
#: backends). Each entry says why.
ALWAYS_TOUCHING: tuple[tuple[str, str, str], ...] = (
    ("left_hip", "right_hip", "inner thighs touch standing"),
    ("left_hip", "spine1", "hip flexion folds the thigh into the lower belly"),
    ("right_hip", "spine1", "hip flexion folds the thigh into the lower belly"),
    ("left_shoulder", "spine2", "armpit: upper arm against the ribs"),
    ("right_shoulder", "spine2", "armpit: upper arm against the ribs"),
    ("left_shoulder", "spine1", "arms at the sides: upper arm against the waist"),
    ("right_shoulder", "spine1", "arms at the sides: upper arm against the waist"),
    ("left_shoulder", "neck", "trapezius: shoulder top meets the neck"),
    ("right_shoulder", "neck", "trapezius: shoulder top meets the neck"),
    ("left_collar", "neck", "collar bones meet the neck"),
    ("right_collar", "neck", "collar bones meet the neck"),
    ("left_collar", "spine2", "collar region over the upper ribs"),
    ("right_collar", "spine2", "collar region over the upper ribs"),
    ("left_collar", "right_collar", "collar bones meet at the sternum"),
    ("left_collar", "head", "chin down onto the collar bones"),
    ("right_collar", "head", "chin down onto the collar bones"),
)


def group_name(joint_name: str) -> str:
    """Collision group of a joint: fingers, hand joints and wrist → `<side>_hand`."""
    merged = default_merge(joint_name)
    return merged.replace("_wrist", "_hand") if merged.endswith("_wrist") else merged


def part_groups(part_names: Sequence[str]) -> tuple[tuple[str, ...], np.ndarray]:
    """(group names, group index of each part)."""
    names = [group_name(n) for n in part_names]
    groups = tuple(dict.fromkeys(names))
    return groups, np.array([groups.index(n) for n in names], dtype=np.int64)


def group_parents(groups: Sequence[str], joint_names: Sequence[str],
                  parents: np.ndarray) -> dict[str, str]:
    """Each group's parent group: the nearest ancestor joint whose group exists and differs."""
    present = set(groups)
    out: dict[str, str] = {}
    for j, name in enumerate(joint_names):
        g = group_name(name)
        if g not in present or g in out:
            continue
        p = int(parents[j])
        while p >= 0 and (group_name(joint_names[p]) == g
                          or group_name(joint_names[p]) not in present):
            p = int(parents[p])
        if p >= 0:
            out[g] = group_name(joint_names[p])
    return out


def checked_pairs(groups: Sequence[str], joint_names: Sequence[str], parents: np.ndarray,
                  allow_pairs: Iterable[Sequence[str]] = ()) -> np.ndarray:
    """(G,G) symmetric bool matrix: True where the pair of groups is checked for collision."""
    index = {g: i for i, g in enumerate(groups)}
    checked = ~np.eye(len(groups), dtype=bool)

    def drop(a: str, b: str) -> None:
        if a in index and b in index:
            checked[index[a], index[b]] = checked[index[b], index[a]] = False

    for child, parent in group_parents(groups, joint_names, parents).items():
        drop(child, parent)
    for a, b, _ in ALWAYS_TOUCHING:
        drop(a, b)
    for pair in allow_pairs:
        if len(pair) != 2:
            raise ConfigError("collision.allow_pairs",
                              f"expected pairs of part names, got {pair!r}")
        for name in pair:
            if name not in index:
                raise ConfigError("collision.allow_pairs",
                                  f"unknown part {name!r}; known: {', '.join(groups)}")
        drop(*pair)
    return checked
