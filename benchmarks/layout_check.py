"""Layout detection on clips the tests never see: synthetic signing (seed 21) written in three
layouts, loaded back, and judged.

Layouts: BEAT2 with its `model` key (y-up, mean-relative hands), the same without `model` (its
keys then read as AMASS: z-up, absolute), and AMASS (z-up, absolute hands). Per layout it counts
clips loaded upright (the loaded body's rest up within 45 deg of +y), clips with correct hands
(loaded hand pose within 1e-4 rad of the clip's), clips with a layout warning, and clips both
wrong and silent. Works on trees without `embody.io.layout` (reports 0 warnings there).

    python benchmarks/layout_check.py [--n 24] [--seed 21]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=24)
    ap.add_argument("--seed", type=int, default=21)
    args = ap.parse_args()

    from embody.io import hand_mean, load
    from embody.io.frames import Z_UP_TO_Y_UP, rotate_root
    from embody.synth.generator import generate_sequence

    stats = {k: {"upright": 0, "hands_ok": 0, "warned": 0, "wrong_silent": 0, "hands_detected": 0}
             for k in ("beat2", "beat2_without_model", "amass")}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.n):
            m = generate_sequence(args.seed, i)
            t = m.num_frames
            pose, transl = m.pose.astype(np.float64), m.transl.astype(np.float64)
            rel = pose.copy()
            rel[:, 25:55] -= hand_mean()
            zpose, ztransl = rotate_root(pose, transl, Z_UP_TO_Y_UP.T)
            common = {"betas": np.zeros(10), "gender": np.array("neutral"),
                      "mocap_frame_rate": np.array(30)}
            files = {"beat2": {"poses": rel.reshape(t, 165), "trans": transl,
                               "model": np.array("smplx2020"), **common},
                     "beat2_without_model": {"poses": rel.reshape(t, 165), "trans": transl, **common},
                     "amass": {"poses": zpose.reshape(t, 165), "trans": ztransl, **common}}
            for layout, arrays in files.items():
                path = Path(tmp) / f"{layout}_{i}.npz"
                np.savez(path, **arrays)
                got = load(path)
                up = Rotation.from_rotvec(got.pose[:, 0].astype(np.float64)).apply([0, 1, 0]).mean(0)
                upright = bool(up[1] > np.cos(np.radians(45)))
                hands_ok = bool(np.abs(got.pose[:, 25:55] - pose[:, 25:55]).max() < 1e-4)
                check = got.source.provenance.get("check", {})
                warned = bool(check.get("warnings"))
                s = stats[layout]
                s["upright"] += upright
                s["hands_ok"] += hands_ok
                s["warned"] += warned
                s["wrong_silent"] += (not (upright and hands_ok)) and not warned
                truth = "absolute" if layout == "amass" else "relative"
                s["hands_detected"] += check.get("hands", {}).get("data") == truth
    for layout, s in stats.items():
        print(f"RESULT layout={layout} n={args.n} " + " ".join(f"{k}={v}" for k, v in s.items()))


if __name__ == "__main__":
    main()
