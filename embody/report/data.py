"""What a report is made of: one run's per-sequence results as plain tables and arrays.

`RunData` is the seam between the store (see `embody.report.reader`) and the report writers, so
the writers can be driven by any source of results, e.g. a notebook's DataFrames.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd


#: Fidelity measures copied to `final.<key>` columns of `sequences.csv` (final trajectory).
FINAL_FIDELITY = ("location_err", "location_err_mm", "location_agree_pct", "palm_deg",
                  "handshape_err", "movement_dtw", "contact_f1")


@dataclass
class RunData:
    """One run's results. Every DataFrame is indexed by sequence id.

    - `sequences`: status ("ok"/"failed"), error and text of every sequence, failed ones included.
    - `collision`: the `embody.collision.mitigate` metrics dict per sequence.
    - `retarget`: the IK-only `IKSolution.metrics` per sequence.
    - `refined`: critic name → the refine step's metrics per sequence (final round, accepted,
      rounds).
    - `critic_ik`: critic name → the critic's metrics of its IK-only round per sequence
      (stored by the metrics step as `critic_ik.*`).
    - `validation`: critic name → validation counters of the refined trajectories.
    - `other`: step name → metrics of the remaining steps (they only go to `sequences.csv`).
    - `ablation`: Table II setting → collision metrics DataFrame (only for `--ablation`).
    - `wrists`: sequence id → {"reference"|"IK only"|"refined": (T,2,3) wrist positions, m}.
    - `sheets`: sequence id → the critic's comparison sheet (PNG bytes).
    - `locations`: sequence id → {"err": (T,2) location error per hand (body scales),
      "landmark": (T,2) index of the human hand's nearest landmark, "names": landmark names,
      "fps": frame rate}, as the metrics step stored them.
    """

    name: str
    sequences: pd.DataFrame
    collision: pd.DataFrame = field(default_factory=pd.DataFrame)
    retarget: pd.DataFrame = field(default_factory=pd.DataFrame)
    refined: dict[str, pd.DataFrame] = field(default_factory=dict)
    critic_ik: dict[str, pd.DataFrame] = field(default_factory=dict)
    validation: dict[str, pd.DataFrame] = field(default_factory=dict)
    other: dict[str, pd.DataFrame] = field(default_factory=dict)
    ablation: dict[str, pd.DataFrame] = field(default_factory=dict)
    wrists: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    wrist_fps: dict[str, float] = field(default_factory=dict)
    sheets: dict[str, bytes] = field(default_factory=dict)
    #: sequence id → (animated preview bytes, file suffix) from the render stage.
    previews: dict[str, tuple[bytes, str]] = field(default_factory=dict)
    locations: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: sequence id → {"torque_ratio": (T,) worst |τ|/limit of the exported array's inverse
    #: dynamics, "palm_err_mm": (T,) worst palm tracking error of the fixed-base replay, "fps"},
    #: as the physics step stored them.
    physics: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: The robot the run retargeted to (its notes are printed under Table III).
    robot: str = ""
    #: How the sequences with figures were chosen (printed on the page when not all have them).
    figure_rule: str = ""

    def verdicts(self) -> pd.DataFrame:
        """processed_ok / export_valid / critic_accepted / physics_valid per sequence, by `embody.verdicts`
        (the same function the run summary applies to the manifest)."""
        from embody.verdicts import VERDICTS, sequence_verdicts

        metrics = self.other.get("metrics", pd.DataFrame())
        physics = self.other.get("physics", pd.DataFrame())
        refined = self.refined[sorted(self.refined)[0]] if self.refined else pd.DataFrame()
        rows = {}
        for sid, status in self.sequences["status"].items():
            seq: dict[str, Any] = {"status": status, "metrics": {}}
            if sid in metrics.index:
                seq["metrics"]["metrics"] = metrics.loc[sid].dropna().to_dict()
            if sid in physics.index:
                seq["metrics"]["physics"] = physics.loc[sid].dropna().to_dict()
            if sid in refined.index and "accepted" in refined:
                seq["metrics"]["refine"] = {"accepted": bool(refined.loc[sid, "accepted"])}
            rows[sid] = sequence_verdicts(seq)
        frame = pd.DataFrame.from_dict(rows, orient="index", columns=list(VERDICTS))
        frame.index.name = "id"
        return frame.astype(object).where(frame.notna(), None)

    def per_sequence(self) -> pd.DataFrame:
        """Every metric of every sequence in one flat table (the `sequences.csv` rows).

        Columns are prefixed with the pipeline step that produced them, as in the store.
        """
        several = len(self.refined) > 1
        parts = [("collide", self.collision), ("retarget", self.retarget)]
        for critic in sorted(self.refined):
            tag = f".{critic}" if several else ""
            parts += [(f"refine{tag}", self.refined[critic]),
                      (f"validation{tag}", self.validation.get(critic, pd.DataFrame()))]
        parts += sorted(self.other.items())
        frame = self.sequences.join(self.verdicts(), how="left")
        for prefix, df in parts:
            if len(df):
                frame = frame.join(df.add_prefix(f"{prefix}."), how="left")
        final = "metrics.fidelity.final"
        if final in frame:  # the final trajectory's fidelity, whichever Table III row it is
            for key in FINAL_FIDELITY:
                frame[f"final.{key}"] = [
                    row.get(f"metrics.fidelity.{row[final]}.{key}") if isinstance(row[final], str) else None
                    for row in frame.to_dict("records")]
        frame.index.name = "id"
        return frame.reset_index()

    @property
    def failures(self) -> list[tuple[str, str]]:
        bad = self.sequences[self.sequences["status"] != "ok"]
        return [(str(i), str(e)) for i, e in zip(bad.index, bad["error"].fillna(""))]
