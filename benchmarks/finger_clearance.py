"""Finger targets with and without the same-hand clearance solve, against the human's handshape.

For each default synthetic sequence (seed 0), the curl-matched finger targets
(`hands.retarget_hands`) and the same after `finger_clearance.clear_fingers` are put on the robot
(arms at rest: the handshape is measured in the hand's own frame) and compared with the human
the way the fidelity benchmark does (`metrics.fidelity.handshape`: per finger flexion error,
hand lengths). Counted per frame: two bodies of one hand (palm and fingers) more than 2 mm
through each other, on the robot's collision geometry (MuJoCo).

    python benchmarks/finger_clearance.py [--n 24]

Ends with `RESULT frames=… pen_frames_before=… pen_frames_after=… deepest_mm_before=…
deepest_mm_after=… handshape_err_before=… handshape_err_after=… ms_per_frame=…`.

Measured 2026-11-29 (s18-fingers, 2 shared cores under load ~8-16, so ms_per_frame is high):
`RESULT frames=3719 pen_frames_before=605 pen_frames_after=0 deepest_mm_before=25.9
deepest_mm_after=0.0 handshape_err_before=0.0931 handshape_err_after=0.0955 ms_per_frame=15.80`.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from embody.body import load_body_model
from embody.config import Config
from embody.metrics.embodiments import human_track, robot_track
from embody.metrics.fidelity import handshape
from embody.retarget.finger_clearance import FingerClearance, clear_fingers
from embody.retarget.hands import retarget_hands
from embody.robot import load_robot
from embody.synth import generate_sequence


def deepest(fc: FingerClearance, q: np.ndarray) -> np.ndarray:
    """Per frame, the deepest same-hand penetration (m, ≥ 0)."""
    out = np.zeros(len(q))
    for t in range(len(q)):
        for h in range(len(fc.hands)):
            dist, _ = fc._contacts(h, q[t])
            out[t] = max(out[t], -dist.min(initial=0.0))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=24)
    args = ap.parse_args()
    cfg = Config()
    robot, body = load_robot(cfg.robot), load_body_model(cfg.body)
    probe = FingerClearance(robot, clearance=0.0)
    frames, pen, err, seconds = 0, {"before": [], "after": []}, {"before": [], "after": []}, 0.0
    for i in range(args.n):
        motion = generate_sequence(0, i)
        human = human_track(motion, body, with_contacts=False)
        hand_q, names = retarget_hands(motion.pose, robot)
        t0 = time.perf_counter()
        cleared = clear_fingers(robot, hand_q, names)
        seconds += time.perf_counter() - t0
        frames += len(hand_q)
        for key, hq in (("before", hand_q), ("after", cleared)):
            q = np.tile(robot.rest, (len(hq), 1))
            q[:, [robot.joint_index(n) for n in names]] = hq
            pen[key].append(deepest(probe, q))
            err[key].append(float(handshape(human, robot_track(robot, q, motion.fps, with_contacts=False))
                                  ["flexion_err"].mean()))
        print(f"seq{i:02d} frames={len(hand_q)} pen>2mm before={int((pen['before'][-1] > 0.002).sum())} "
              f"after={int((pen['after'][-1] > 0.002).sum())} handshape_err before={err['before'][-1]:.4f} "
              f"after={err['after'][-1]:.4f}", flush=True)
    cat = {k: np.concatenate(v) for k, v in pen.items()}
    print(f"RESULT frames={frames} pen_frames_before={int((cat['before'] > 0.002).sum())} "
          f"pen_frames_after={int((cat['after'] > 0.002).sum())} "
          f"deepest_mm_before={1e3 * cat['before'].max():.1f} deepest_mm_after={1e3 * cat['after'].max():.1f} "
          f"handshape_err_before={np.mean(err['before']):.4f} handshape_err_after={np.mean(err['after']):.4f} "
          f"ms_per_frame={1e3 * seconds / max(frames, 1):.2f}")


if __name__ == "__main__":
    main()
