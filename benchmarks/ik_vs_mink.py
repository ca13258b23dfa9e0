"""Our whole-sequence IK vs mink (the IK behind GMR) on the same robot, targets and sequences.

Input is what the pipeline feeds the IK: synthetic sequences after stage 1 collision mitigation
(`embody.collision.mitigate`, default config; its time is not counted). Both solvers get the
same targets: `build_targets` without an IK config, i.e. the plain shape-fit targets
(`ik.location_preserving` off, so no anchored hand points and every wrist weight 1): both solvers
chase exactly the wrist poses they are scored against, which is the fair IK-vs-IK comparison
(the pipeline's location-preserving targets deliberately move the wrist off these near landmarks
and are scored by the fidelity metrics instead). Wrist errors are reported on all frames, and (extra keys) on *clean* frames, where
mink's pure tracking is free of MuJoCo contacts (no solver had to avoid a collision there), and on
*feasible* frames, clean ones that mink also reaches within the velocity limits. Our time
includes MuJoCo verification (`IKSolution.metrics` carries the contact counts). Our solver also
runs with its other FK backend (`IKConfig.kinematics`: pytorch-kinematics or the NumPy tree):
`ours_<other>_fps`, and `backend_max_dq`, the largest joint difference between the two solutions.

mink runs per frame like GMR: FrameTasks for both wrists (and elbows, position only), a
PostureTask, `solve_ik(..., solver="daqp", limits=[ConfigurationLimit, VelocityLimit])` with
`limits=` passed BY KEYWORD (GMR passes it positionally, so its velocity limits never apply),
10 iterations per frame. The robot base is fixed for both (mink gets the MJCF without its free
joint), legs are pinned, and fingers take the same retargeted hand values, so contacts compare.

The strongest mink (`mink_collision`, `mink_col` in the table) is the same plus mink's own
`CollisionAvoidanceLimit` (gain 0.85, 5 mm minimum distance, 10 mm detection distance) in
`limits=`, on the geom pairs our proxies guard (`proxy_pairs` of the robot YAML: hands, forearms
and upper arms against each other, the torso shell, the head, pelvis and thighs), restricted to the
pairs MuJoCo's verdict counts (`counted_geom_pairs`). Its clean/feasible frames are its own; the
`feasible` keys of ours and mink's stay on the plain mink's feasible frames.

Collision frames are counted at the source rate (`*_collision_frames`, the frames each solver
solved) and on the trajectory a robot executes: linearly resampled to the control rate
(`ik.control_rate_hz`, 50 Hz; `*_collision_frames_50hz`), where hands that are clear at two
source frames can still pass through each other between them. Ours checks those samples inside
its contact phase (`ik.contact_samples`, on by default); `--ik contact_samples=false` is the
source-rate-only solver (faster, not clear at 50 Hz). `ours_export_collision_frames_50hz` counts
the same on what ours exports (`IKSolution.q_control`: resampled, then every sample repaired and
validated), the trajectory a robot is given.

Frames per second are wall clock (`*_fps`, `fps_ratio*`, as the issue states them) and process
CPU time (`*_cpu_fps`, `fps_ratio*_cpu`: every solver runs single-threaded, so on a shared,
loaded machine the CPU ratio is the one that does not move with the other processes).

Usage: python benchmarks/ik_vs_mink.py [--sequences 4] [--seed 0] [--profile ik.pstats] [--config FILE ...]
[--ik KEY=VALUE ...]
(`--profile`: cProfile of our solves only, saved there, top entries printed before the RESULT line;
`--config`: our solver's `ik` section from a config file, e.g. `--config configs/ik/tracking.yaml`,
the plain-tracking preset, whose task is exactly this benchmark's; mink keeps the default's weights;
`--ik`: override an `ik` config field of our solver, e.g. `--ik polish_iterations=0` for an A/B).
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import fnmatch
import time
import xml.etree.ElementTree as ET
from collections import Counter

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import mink  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from embody.body import load_body_model  # noqa: E402
from embody.collision import mitigate  # noqa: E402
from embody.config import Config, load_config  # noqa: E402
from embody.config.ik import IKConfig  # noqa: E402
from embody.retarget import build_targets, shape_fit, solve  # noqa: E402
from embody.retarget.ik import evaluate  # noqa: E402
from embody.retarget.limits import resample  # noqa: E402
from embody.retarget.targets import Targets  # noqa: E402
from embody.robot import Robot, load_robot  # noqa: E402
from embody.robot.contacts import contact_pairs, counted_geom_pairs, self_collision_contacts  # noqa: E402
from embody.synth import generate_sequence  # noqa: E402


def fixed_base_model(robot: Robot) -> mujoco.MjModel:
    """The robot's MJCF without its free joint; legs and fingers pinned to a tiny range."""
    root = ET.parse(robot.mjcf_path).getroot()
    for parent in root.iter():
        for child in list(parent):
            if child.tag == "freejoint" or (child.tag == "joint" and child.get("type") == "free"):
                parent.remove(child)
    compiler = root.find("compiler")
    if compiler is not None and compiler.get("meshdir"):
        compiler.set("meshdir", str(robot.mjcf_path.parent / compiler.get("meshdir")))
    for key in root.findall("keyframe"):
        root.remove(key)
    model = mujoco.MjModel.from_xml_string(ET.tostring(root, encoding="unicode"))
    for j, name in enumerate(robot.joint_names):
        jid = model.joint(name).id
        assert model.jnt_qposadr[jid] == j, "hinge order must match"
        if not robot.ik_mask[j]:
            model.jnt_range[jid] = (robot.rest[j] - 1e-6, robot.rest[j] + 1e-6)
            model.jnt_limited[jid] = 1
    return model


def proxy_geom_pairs(robot: Robot, model: mujoco.MjModel) -> list[tuple[list[int], list[int]]]:
    """Collision geom pairs (one per pair, for `CollisionAvoidanceLimit`) between the bodies of
    each of the robot's `proxy_pairs`, kept only where MuJoCo's self-collision verdict counts them."""
    groups = set(robot.spec.collision.geom_groups)
    names = [model.body(b).name for b in range(model.nbody)]

    def geoms(proxy: str) -> list[int]:
        pats = robot.spec.proxies[proxy].bodies
        return [g for g in range(model.ngeom) if model.geom_group[g] in groups
                and any(fnmatch.fnmatchcase(names[model.geom_bodyid[g]], p) for p in pats)]

    counted = counted_geom_pairs(robot)  # same geom ids: removing the free joint keeps geoms
    assert model.ngeom == robot.model.ngeom
    out = set()
    for a, b in robot.spec.proxy_pairs:
        out.update((min(i, j), max(i, j)) for i in geoms(a) for j in geoms(b) if i != j and counted[i, j])
    return [([i], [j]) for i, j in sorted(out)]


def run_mink(robot: Robot, model: mujoco.MjModel, targets: Targets, iterations: int = 10,
             collision_pairs: list | None = None) -> np.ndarray:
    world_from_torso = np.linalg.inv(robot.torso_from_world)
    conf = mink.Configuration(model, q=robot.rest.copy())
    cfg = IKConfig()
    wrists = [mink.FrameTask(robot.spec.links[f"{s}_wrist"].body, "body", position_cost=1.0,
                             orientation_cost=float(np.sqrt(cfg.w_wrist_rot / cfg.w_wrist_pos)), lm_damping=1.0)
              for s in ("left", "right")]
    elbows = [mink.FrameTask(robot.spec.links[f"{s}_elbow"].body, "body",
                             position_cost=float(np.sqrt(cfg.w_elbow_pos)), orientation_cost=0.0)
              for s in ("left", "right")]
    posture = mink.PostureTask(model, cost=1e-2)
    posture.set_target(robot.rest.copy())
    tasks = [*wrists, *elbows, posture]
    limits = [mink.ConfigurationLimit(model),
              mink.VelocityLimit(model, {n: float(v) for n, v, m in
                                         zip(robot.joint_names, robot.velocity_limits, robot.ik_mask) if m})]
    if collision_pairs:
        limits.append(mink.CollisionAvoidanceLimit(model, geom_pairs=collision_pairs, gain=0.85,
                                                   minimum_distance_from_collisions=0.005,
                                                   collision_detection_distance=0.01))
    dt = 1.0 / targets.fps
    out = np.zeros((targets.num_frames, robot.n_joints))
    cols = [robot.joint_index(n) for n in targets.hand_joints] if targets.hand_joints else []
    hand_q = np.clip(targets.hand_q, robot.lower[cols], robot.upper[cols]) if cols else None
    for t in range(targets.num_frames):
        if cols:  # the fingers are where ours are at every frame (pinned), so contacts compare
            limits[0].lower[cols], limits[0].upper[cols] = hand_q[t] - 1e-6, hand_q[t] + 1e-6
            q = conf.q.copy()
            q[cols] = hand_q[t]
            conf.update(q=q)
        for k, task in enumerate(wrists):
            pose = np.eye(4)
            pose[:3, :3] = targets.wrist_rot[t, k]
            pose[:3, 3] = targets.wrist_pos[t, k]
            task.set_target(mink.SE3.from_matrix(world_from_torso @ pose))
        for k, task in enumerate(elbows):
            pose = np.eye(4)
            pose[:3, 3] = targets.elbow_pos[t, k]
            task.set_target(mink.SE3.from_matrix(world_from_torso @ pose))
        for _ in range(iterations):
            vel = mink.solve_ik(conf, tasks, dt, solver="daqp", damping=1e-3, limits=limits)
            conf.integrate_inplace(vel, dt)
        out[t] = conf.q
    if cols:  # exactly the same fingers as ours
        out[:, cols] = hand_q
    return out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--sequences", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--profile", default=None, help="save a cProfile of our solves here")
    parser.add_argument("--config", action="append", default=[], metavar="FILE",
                        help="our solver's `ik` section from this config file (repeatable; e.g. "
                             "configs/ik/tracking.yaml); mink and the inputs keep the defaults")
    parser.add_argument("--ik", action="append", default=[], metavar="KEY=VALUE",
                        help="override an ik config field of our solver (repeatable)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    config = Config()
    robot, body = load_robot(config.robot), load_body_model(config.body)
    # our solver's config: the files, then the `ik` overrides, as `embody run` merges them
    cfg = load_config(args.config, sets=[f"ik.{kv}" for kv in args.ik]).ik
    other = "tree" if cfg.kinematics == "pytorch_kinematics" else "pytorch_kinematics"
    cfg_other = cfg.model_copy(update={"kinematics": other})
    other_key = {"tree": "tree", "pytorch_kinematics": "pk"}[other]
    fit = shape_fit(robot, body, cfg)
    model = fixed_base_model(robot)
    seqs = [mitigate(generate_sequence(args.seed, i), body, config.collision).motion for i in range(args.sequences)]
    all_targets = [build_targets(m, body, fit, robot) for m in seqs]
    for c in (cfg, cfg_other):  # warm-up (proxies, caches, pk chains)
        solve(robot, all_targets[0], c.model_copy(update={"iterations": 1}))
    geom_pairs = proxy_geom_pairs(robot, model)
    print(f"mink_col: CollisionAvoidanceLimit on {len(geom_pairs)} geom pairs")
    run_mink(robot, model, all_targets[0], iterations=1)
    run_mink(robot, model, all_targets[0], iterations=1, collision_pairs=geom_pairs)
    profiler = cProfile.Profile() if args.profile else None
    totals = {k: 0.0 for k in ("ours_t", "other_t", "mink_t", "mink_col_t", "frames")}
    cpu = {k: 0.0 for k in ("ours", "mink", "mink_col")}  # process CPU time: robust to other load
    max_dq = 0.0
    rows: dict[str, list[dict]] = {"ours": [], "mink": [], "mink_col": []}
    errs: dict[str, dict[str, list[np.ndarray]]] = {
        n: {"all": [], "clean": [], "feasible": [], "feasible_col": []} for n in rows}
    pairs = {n: Counter() for n in rows}
    at_rate = {n: 0 for n in rows}  # frames with a penetrating contact on the 50 Hz resampled trajectory
    exported = 0  # the same on our exported control-rate trajectory (`IKSolution.q_control`)
    rate_frames = 0
    print(f"{'seq':>4} {'frames':>6} {'solver':>6} {'fps':>8} {'wrist_mm':>9} {'rot_deg':>8} {'jerk':>9} "
          f"{'vel_viol':>8} {'coll_frames':>11} {'clean_mm':>9}")
    for i, targets in enumerate(all_targets):
        if profiler is not None:
            profiler.enable()
        c0, t0 = time.process_time(), time.perf_counter()
        ours = solve(robot, targets, cfg)
        c1, t1 = time.process_time(), time.perf_counter()
        if profiler is not None:
            profiler.disable()
        theirs = run_mink(robot, model, targets)
        c2, t2 = time.process_time(), time.perf_counter()
        again = solve(robot, targets, cfg_other)
        c3, t3 = time.process_time(), time.perf_counter()
        theirs_col = run_mink(robot, model, targets, collision_pairs=geom_pairs)
        c4, t4 = time.process_time(), time.perf_counter()
        cpu["ours"] += c1 - c0
        cpu["mink"] += c2 - c1
        cpu["mink_col"] += c4 - c3
        totals["ours_t"] += t1 - t0
        totals["mink_t"] += t2 - t1
        totals["other_t"] += t3 - t2
        totals["mink_col_t"] += t4 - t3
        max_dq = max(max_dq, float(np.abs(again.q - ours.q).max()))
        totals["frames"] += targets.num_frames
        rate_frames += len(resample(ours.q, targets.fps, cfg.control_rate_hz))
        exported += int((self_collision_contacts(robot, np.asarray(ours.q_control)) > 0).sum())
        frames_m, m_mink = evaluate(robot, theirs, targets)
        frames_c, m_col = evaluate(robot, theirs_col, targets)
        results = {"ours": (ours.q, ours.frame_metrics, ours.metrics, t1 - t0),
                   "mink": (theirs, frames_m, m_mink, t2 - t1),
                   "mink_col": (theirs_col, frames_c, m_col, t4 - t3)}

        def feasible_of(q: np.ndarray, frames: dict) -> np.ndarray:
            """Frames free of MuJoCo contacts, reached within the velocity limits."""
            step_ok = np.ones(len(q), dtype=bool)
            step_ok[1:] = (np.abs(np.diff(q, axis=0)) * targets.fps <= robot.velocity_limits * (1 + 1e-9)).all(1)
            return (frames["self_contacts"] == 0) & step_ok

        clean = frames_m["self_contacts"] == 0
        feasible = feasible_of(theirs, frames_m)
        feasible_col = feasible_of(theirs_col, frames_c)
        for name, (q, frames, m, dt) in results.items():
            rows[name].append(m)
            at_rate[name] += int((self_collision_contacts(robot, resample(q, targets.fps, cfg.control_rate_hz)) > 0).sum())
            pairs[name].update(contact_pairs(robot, q))
            wrist = frames["wrist_pos_err_mm"].mean(1)
            for key, sel in (("all", slice(None)), ("clean", clean), ("feasible", feasible),
                             ("feasible_col", feasible_col)):
                errs[name][key].append(wrist[sel])
            print(f"{i:>4} {targets.num_frames:>6} {name:>6} {targets.num_frames / dt:>8.1f} "
                  f"{m['wrist_pos_err_mm']:>9.2f} {m['wrist_rot_err_deg']:>8.2f} {m['jerk']:>9.1f} "
                  f"{int(m['velocity_violations']):>8} {int(m['self_collision_frames']):>11} "
                  f"{wrist[clean].mean() if clean.any() else float('nan'):>9.2f}")
        print(f"{i:>4} {targets.num_frames:>6} {other_key:>6} {targets.num_frames / (t3 - t2):>8.1f} "
              f"{again.metrics['wrist_pos_err_mm']:>9.2f} {again.metrics['wrist_rot_err_deg']:>8.2f} "
              f"{again.metrics['jerk']:>9.1f} {int(again.metrics['velocity_violations']):>8} "
              f"{int(again.metrics['self_collision_frames']):>11}")

    def mean(name: str, key: str) -> float:
        return float(np.mean([m[key] for m in rows[name]]))

    def frames_mean(name: str, key: str) -> float:
        e = np.concatenate(errs[name][key])
        return float(e.mean()) if len(e) else float("nan")

    for name in pairs:
        print(f"contact frames by body pair ({name}):",
              ", ".join(f"{a}/{b}={n}" for (a, b), n in pairs[name].most_common(6)) or "none")
    n_clean, n_feasible, n_col = (len(np.concatenate(errs["ours"][k])) for k in ("clean", "feasible", "feasible_col"))
    print(f"clean frames {n_clean}, feasible frames {n_feasible} (mink), {n_col} (mink_col) "
          f"of {int(totals['frames'])}")
    print(f"collision frames at {cfg.control_rate_hz:g} Hz (of {rate_frames}): "
          + ", ".join(f"{n} {at_rate[n]}" for n in rows))
    ours_fps = totals["frames"] / totals["ours_t"]
    mink_fps = totals["frames"] / totals["mink_t"]
    col_fps = totals["frames"] / totals["mink_col_t"]
    print(f"mink_col {col_fps:.1f} fps, wrist {mean('mink_col', 'wrist_pos_err_mm'):.2f} mm, "
          f"ours on its feasible frames {frames_mean('ours', 'feasible_col'):.2f} mm")
    other_fps = totals["frames"] / totals["other_t"]
    print(f"ours ({cfg.kinematics}) {ours_fps:.1f} fps, ours ({other}) {other_fps:.1f} fps, "
          f"max |dq| between them {max_dq:.2e} rad")
    if profiler is not None:
        profiler.dump_stats(args.profile)
        pstats.Stats(profiler).sort_stats("cumulative").print_stats(25)
    coll = {n: int(sum(m["self_collision_frames"] for m in rows[n])) for n in rows}
    print(f"RESULT ours_fps={ours_fps:.1f} mink_fps={mink_fps:.1f} fps_ratio={ours_fps / mink_fps:.3f} "
          f"ours_wrist_mm={mean('ours', 'wrist_pos_err_mm'):.2f} mink_wrist_mm={mean('mink', 'wrist_pos_err_mm'):.2f} "
          f"ours_rot_deg={mean('ours', 'wrist_rot_err_deg'):.2f} mink_rot_deg={mean('mink', 'wrist_rot_err_deg'):.2f} "
          f"ours_jerk={mean('ours', 'jerk'):.1f} mink_jerk={mean('mink', 'jerk'):.1f} "
          f"ours_collision_frames={coll['ours']} mink_collision_frames={coll['mink']} "
          f"ours_collision_frames_50hz={at_rate['ours']} mink_collision_frames_50hz={at_rate['mink']} "
          f"ours_export_collision_frames_50hz={exported} "
          f"mink_collision_frames_50hz_with_limit={at_rate['mink_col']} "
          f"ours_clean_wrist_mm={frames_mean('ours', 'clean'):.2f} mink_clean_wrist_mm={frames_mean('mink', 'clean'):.2f} "
          f"ours_feasible_wrist_mm={frames_mean('ours', 'feasible'):.2f} "
          f"mink_feasible_wrist_mm={frames_mean('mink', 'feasible'):.2f} "
          f"ours_vel_viol={mean('ours', 'velocity_violations'):.1f} "
          f"mink_vel_viol={mean('mink', 'velocity_violations'):.1f} "
          f"ours_{other_key}_fps={other_fps:.1f} backend_max_dq={max_dq:.2e} "
          f"mink_collision_fps={col_fps:.1f} fps_ratio_mink_collision={ours_fps / col_fps:.3f} "
          f"mink_collision_wrist_mm={mean('mink_col', 'wrist_pos_err_mm'):.2f} "
          f"mink_collision_frames_with_limit={coll['mink_col']} "
          f"mink_collision_feasible_wrist_mm={frames_mean('mink_col', 'feasible_col'):.2f} "
          f"ours_collision_feasible_wrist_mm={frames_mean('ours', 'feasible_col'):.2f} "
          f"mink_collision_vel_viol={mean('mink_col', 'velocity_violations'):.1f} "
          f"ours_cpu_fps={totals['frames'] / cpu['ours']:.1f} mink_cpu_fps={totals['frames'] / cpu['mink']:.1f} "
          f"mink_collision_cpu_fps={totals['frames'] / cpu['mink_col']:.1f} "
          f"fps_ratio_cpu={cpu['mink'] / cpu['ours']:.3f} "
          f"fps_ratio_mink_collision_cpu={cpu['mink_col'] / cpu['ours']:.3f}")


if __name__ == "__main__":
    main()
