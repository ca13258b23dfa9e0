"""Sign fidelity on the default synthetic set: IK-only vs location-preserving vs refined.

Each sequence goes through the pipeline's own library calls (collision mitigation, shape fit,
IK with shape-fit targets only, IK with location-preserving targets, the geometric critic's
refinement) and is compared with the human it retargets by `embody.metrics.fidelity`. Then one
sequence per lexicon location (forehead, chin, cheek, chest, opposite shoulder, ...) checks the
generator's own ground truth: during each sign's hold (its middle third) the robot palm's offset
from the robot landmark of the sign's location must match the human palm's offset from the
human's landmark of that name (offsets per body scale, reported in robot cm).

    python benchmarks/fidelity.py [--n 24] [--no-refine] [--no-locations]

Ends with `RESULT location_err_ik=… location_err_preserving=… location_err_refined=…
location_agree_pct=… contact_f1=… palm_deg=… handshape_err=… penetration_frames=… seconds_per_seq=…`
(location errors in body scales; agreement, F1, palm, handshape and penetrations of the final
trajectory: refined when refining, else location-preserving).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from embody.body import load_body_model
from embody.collision import mitigate
from embody.config import Config
from embody.critic import refine
from embody.metrics.embodiments import human_track, robot_track
from embody.metrics.fidelity import compare_with, relative_location
from embody.retarget import build_targets, shape_fit, solve
from embody.retarget.validation import validation_counts
from embody.robot import load_robot
from embody.synth.generator import generate_sequence
from embody.synth.lexicon import LEXICON

#: Lexicon location → the landmark it names (the dominant hand is the right one).
LOCATION_LANDMARK = {"forehead": "forehead", "chin": "chin", "cheek": "right_cheek",
                     "chest": "sternum", "opposite_shoulder": "left_shoulder"}


def pooled_f1(rows: list[dict[str, float]], prefix: str) -> float:
    tp = sum(r[f"{prefix}contact_tp"] for r in rows)
    hp = sum(r[f"{prefix}contact_frames_human"] for r in rows)
    rp = sum(r[f"{prefix}contact_frames_robot"] for r in rows)
    p, r = (tp / rp if rp else np.nan), (tp / hp if hp else np.nan)
    return float(2 * p * r / (p + r)) if rp and hp and p + r > 0 else float("nan")


def run_sequence(motion, cfg: Config, body, robot, fit, do_refine: bool) -> tuple[dict, dict]:
    """All three rows' fidelity of one sequence, plus the human and final robot tracks."""
    motion = mitigate(motion, body, cfg.collision).motion
    human = human_track(motion, body)
    out: dict[str, float] = {}
    plain = cfg.ik.model_copy(update={"location_preserving": False})
    rows = {"ik": solve(robot, build_targets(motion, body, fit, robot, plain), plain)}
    targets = build_targets(motion, body, fit, robot, cfg.ik)
    rows["preserving"] = solve(robot, targets, cfg.ik)
    qs = {k: v.q for k, v in rows.items()}
    if do_refine:
        qs["refined"] = refine(motion, body, fit, robot, targets, rows["preserving"], cfg.critic, cfg.ik,
                               cfg.render).q
    tracks = {}
    for name, q in qs.items():
        tracks[name] = robot_track(robot, q, motion.fps)
        _, m = compare_with(human, tracks[name], cfg.fidelity)
        out.update({f"{name}.{k}": v for k, v in m.items()})
        v = validation_counts(robot, q, motion.fps)
        out.update({f"{name}.{k}": v[k] for k in v})
    return out, {"human": human, **tracks, "motion": motion}


def hold_offsets(tracks: dict, final: str) -> list[tuple[str, float]]:
    """Per sign at a named location: |robot − human| palm offset from that landmark (robot cm)."""
    motion, human, robot = tracks["motion"], tracks["human"], tracks[final]
    out = []
    for sign in motion.meta.get("signs", []):
        lname = LOCATION_LANDMARK.get(sign.get("location", ""))
        if lname is None:
            continue
        a, b = sign["start"], sign["end"]
        hold = slice(a + (b - a) // 3, b - (b - a) // 3)
        names = [lname]
        k = np.zeros(len(human.points), dtype=int)
        vh = relative_location(human, "right", names, k)[hold]
        vr = relative_location(robot, "right", names, k)[hold]
        out.append((sign["location"], float(np.linalg.norm(vh - vr, axis=-1).mean() * robot.scale * 100)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=24, help="default synthetic sequences (seed 0)")
    ap.add_argument("--no-refine", action="store_true")
    ap.add_argument("--no-locations", action="store_true")
    args = ap.parse_args()
    cfg = Config()
    body, robot = load_body_model(cfg.body), load_robot(cfg.robot)
    fit = shape_fit(robot, body, cfg.ik)
    final = "preserving" if args.no_refine else "refined"
    rows, seconds = [], []
    for i in range(args.n):
        t0 = time.perf_counter()
        m, _ = run_sequence(generate_sequence(0, i), cfg, body, robot, fit, not args.no_refine)
        seconds.append(time.perf_counter() - t0)
        rows.append(m)
        print(f"seq{i:02d} " + " ".join(f"{k}={m[f'{k2}.location_err']:.3f}" for k, k2 in
                                       (("ik", "ik"), ("pres", "preserving"), ("final", final)))
              + f" agree={m[f'{final}.location_agree_pct']:.1f} palm={m[f'{final}.palm_deg']:.1f}"
              f" hand={m[f'{final}.handshape_err']:.3f} self_coll={m[f'{final}.self_collision_frames']:.0f}"
              f" vel={m[f'{final}.velocity_violations']:.0f} {seconds[-1]:.0f}s", flush=True)
    checks: list[tuple[str, bool, str]] = []  # (issue target, met, measured)
    if not args.no_locations:
        seen = set()
        for j, sign in enumerate(LEXICON):
            if sign.location in seen:
                continue
            seen.add(sign.location)
            _, tracks = run_sequence(generate_sequence(1, 1000 + j, signs=[sign]), cfg, body, robot, fit,
                                     False)
            for loc, cm in hold_offsets(tracks, "preserving"):
                cm_ik = dict(hold_offsets(tracks, "ik"))[loc]
                print(f"location {loc:18s} ({sign.gloss}): hold offset error ik={cm_ik:.1f} cm "
                      f"preserving={cm:.1f} cm")
                checks.append((f"hold offset at {loc} <= 3 cm", cm <= 3.0, f"{cm:.1f} cm"))

    def mean(key: str) -> float:
        return float(np.nanmean([r[key] for r in rows]))

    print(" ".join(f"{row}: self_coll={sum(r[f'{row}.self_collision_frames'] for r in rows):.0f} "
                   f"limit={sum(r[f'{row}.joint_limit_violations'] for r in rows):.0f} "
                   f"vel={sum(r[f'{row}.velocity_violations'] for r in rows):.0f} "
                   f"contact_f1={pooled_f1(rows, f'{row}.'):.3f}"
                   for row in ("ik", "preserving", *([] if args.no_refine else ["refined"]))))
    refined = mean("refined.location_err") if not args.no_refine else float("nan")
    total = lambda key: sum(r[f"{final}.{key}"] for r in rows)  # noqa: E731
    f1, agree = pooled_f1(rows, f"{final}."), mean(f"{final}.location_agree_pct")
    checks += [
        ("location agreement >= 90 %", agree >= 90.0, f"{agree:.1f} %"),
        ("contact F1 >= 0.9", f1 >= 0.9, f"{f1:.3f}"),
        ("0 robot penetration frames", total("penetration_frames") == 0, f"{total('penetration_frames'):.0f}"),
        ("refined location err <= 0.7 x IK-only", refined <= 0.7 * mean("ik.location_err"),
         f"{refined:.3f} vs {mean('ik.location_err'):.3f}"),
        ("0 joint-limit violations", total("joint_limit_violations") == 0, f"{total('joint_limit_violations'):.0f}"),
        ("0 velocity violations", total("velocity_violations") == 0, f"{total('velocity_violations'):.0f}"),
        (f"self-collision frames <= 9 (24 seqs; here {len(rows)})", total("self_collision_frames") <= 9,
         f"{total('self_collision_frames'):.0f}"),
    ]
    for name, ok, value in checks:
        print(f"TARGET {'PASS' if ok else 'FAIL'} {name}: {value}")
    print(f"RESULT location_err_ik={mean('ik.location_err'):.3f} "
          f"location_err_preserving={mean('preserving.location_err'):.3f} "
          f"location_err_refined={refined:.3f} "
          f"location_agree_pct={mean(f'{final}.location_agree_pct'):.1f} "
          f"contact_f1={pooled_f1(rows, f'{final}.'):.3f} palm_deg={mean(f'{final}.palm_deg'):.2f} "
          f"handshape_err={mean(f'{final}.handshape_err'):.3f} "
          f"penetration_frames={sum(r[f'{final}.penetration_frames'] for r in rows):.0f} "
          f"seconds_per_seq={np.mean(seconds):.1f}")


if __name__ == "__main__":
    main()
