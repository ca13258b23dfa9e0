"""Frame rate, up axis and hand convention of a source, and where each came from.

Readers say what they found (`Setting(value, origin)`: from the data, from a detected layout, or a
documented per-dataset default); the user's overrides (`--fps`, `--up-axis`, `--hands`, config
`io.*`) win over all of them. `normalise` then converts once, in one place, to embody's
conventions (y-up, absolute hands) and records the provenance on the motion, so `inspect` can say
why a clip is read at 24 fps and a wrong guess is visible rather than silent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from embody.errors import InputError
from embody.io.frames import CAMERA_TO_Y_UP, Z_UP_TO_Y_UP, rotate_root
from embody.io.hands import relative_to_absolute

#: Up axes a source can have. "camera" is the OpenCV camera frame of video fits (y down).
UP_AXES = ("y", "z", "camera")
HANDS = ("absolute", "relative")
_ROTATION = {"y": None, "z": Z_UP_TO_Y_UP, "camera": CAMERA_TO_Y_UP}


@dataclass(frozen=True)
class Setting:
    """One convention of a source: its value and a short phrase saying where it came from."""

    value: Any
    origin: str


@dataclass(frozen=True)
class Overrides:
    """User overrides; None keeps what the file or its dataset's default says."""

    fps: float | None = None
    up_axis: str | None = None
    hands: str | None = None

    @classmethod
    def from_config(cls, io: Any) -> "Overrides":
        """From the `io` config section (`io.fps`, `io.up_axis`, `io.hands`)."""
        return cls(fps=io.fps, up_axis=io.up_axis, hands=io.hands)

    def check(self, path: Path) -> None:
        if self.fps is not None and not (isinstance(self.fps, (int, float))
                                         and math.isfinite(self.fps) and self.fps > 0):
            raise InputError(path, "fps", f"must be a positive number, got {self.fps!r}")
        if self.up_axis is not None and self.up_axis not in UP_AXES:
            raise InputError(path, "up_axis", f"expected one of {', '.join(UP_AXES)}, got {self.up_axis!r}")
        if self.hands is not None and self.hands not in HANDS:
            raise InputError(path, "hands", f"expected 'absolute' or 'relative', got {self.hands!r}")


def _pick(found: Setting, override: Any, flag: str) -> Setting:
    if override is None:
        return found
    return Setting(override, f"override ({flag}; the source said {found.value!r}: {found.origin})")


def layout_check(pose: np.ndarray, up_axis: Setting, hands: Setting,
                 overrides: Overrides) -> dict[str, Any]:
    """What the data says about the up axis and hands (`embody.io.layout`) against what the
    file's keys or its dataset's default say, and a warning naming the override that settles
    each disagreement, or each ambiguity of a setting nothing in the file vouches for. An
    override given for a setting settles it; embody's own files are not re-judged.

    Returns {"up_axis"|"hands": {"data", "detail"}, "warnings": [...]} for what was judged.
    """
    from embody.io.layout import detect_hands, detect_up_axis

    pose = np.asarray(pose)
    out: dict[str, Any] = {}
    warnings: list[str] = []
    for name, found, given, flag, choices, detect in (
            ("up_axis", up_axis, overrides.up_axis, "--up-axis", "y|z|camera",
             lambda: detect_up_axis(pose[:, 0])),
            ("hands", hands, overrides.hands, "--hands", "absolute|relative",
             lambda: detect_hands(pose))):
        if "embody_meta" in found.origin:
            continue
        finding = detect()
        if finding is None:
            continue
        out[name] = {"data": finding.value, "detail": finding.detail}
        if given is not None:
            continue
        label = "up axis" if name == "up_axis" else "hand convention"
        # the text names no clip and no measurement, so a run can say each warning once;
        # the measurement is `detail` (inspect prints it)
        if finding.value is None and found.origin.startswith("default"):
            warnings.append(f"{label} {found.value!r} is a default ({found.origin}) that the data "
                            f"cannot confirm; if the motion looks wrong, {flag} {choices} "
                            f"(io.{name}) settles it")
        elif finding.value is not None and finding.value != found.value:
            warnings.append(f"{label}: the file says {found.value!r} ({found.origin}) but the data "
                            f"says {finding.value!r}; {flag} {finding.value} (io.{name}) reads it "
                            f"as the data says, {flag} {found.value} keeps it")
    if out:
        out["warnings"] = warnings
    return out


def layout_warnings(provenance: dict[str, Any]) -> list[str]:
    """The layout warnings a motion's provenance carries (empty when keys and data agree)."""
    return list(provenance.get("check", {}).get("warnings", []))


def normalise(pose: np.ndarray, transl: np.ndarray, *, fps: Setting, up_axis: Setting,
              hands: Setting, overrides: Overrides | None = None
              ) -> tuple[np.ndarray, np.ndarray, float, str, dict[str, dict[str, Any]]]:
    """Source-convention pose (T,55,3) and translation → y-up, absolute hands.

    Returns pose, translation, fps, the source's hand convention and the provenance record
    `{"fps"|"up_axis"|"hands": {"value", "origin"}}`.
    """
    ov = overrides or Overrides()
    check = layout_check(pose, up_axis, hands, ov)
    fps = _pick(fps, None if ov.fps is None else float(ov.fps), "--fps / io.fps")
    up_axis = _pick(up_axis, ov.up_axis, "--up-axis / io.up_axis")
    hands = _pick(hands, ov.hands, "--hands / io.hands")
    pose = np.asarray(pose, dtype=np.float32)
    if hands.value == "relative":
        pose = relative_to_absolute(pose)
    rotation = _ROTATION[up_axis.value]
    if rotation is not None:
        pose, transl = rotate_root(pose, transl, rotation)
    provenance: dict[str, Any] = {name: {"value": s.value, "origin": s.origin}
                                  for name, s in (("fps", fps), ("up_axis", up_axis), ("hands", hands))}
    if check:
        provenance["check"] = check
    return pose, np.asarray(transl, dtype=np.float32), float(fps.value), str(hands.value), provenance
