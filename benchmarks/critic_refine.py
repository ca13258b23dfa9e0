"""The critic on a stored run: this tree's refine loop against the run's stored refine results.

Reads a run's mitigated motions, shape fit and IK-only solutions from a store (read-only), reruns
`embody.critic.refine` with the run's config (this tree's code) and prints, per sequence, the
stored and the new acceptance, chosen round and the chosen round's location error (body scales)
and palm angle, then one RESULT line:

    python benchmarks/critic_refine.py --store embody-store \\
        --run synth-n24-s0.unitree_g1_dex3 [--limit 6] [--rounds-detail]

CPU seconds are `time.process_time` of the refine calls (the store reads are not counted).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--store", default="embody-store")
    ap.add_argument("--run", default="synth-n24-s0.unitree_g1_dex3")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--rounds-detail", action="store_true")
    args = ap.parse_args()

    import torch

    from embody.body import load_body_model
    from embody.collision import CollisionResult
    from embody.config import Config
    from embody.critic import RefineResult, refine
    from embody.retarget import IKSolution, ShapeFit, build_targets
    from embody.robot import load_robot
    from embody.store.artifacts import ArtifactStore

    torch.set_num_threads(1)
    manifest = json.loads((Path(args.store) / "runs" / args.run / "manifest.json").read_text())
    cfg = Config.model_validate(manifest["config"])
    store = ArtifactStore(args.store)
    body, robot = load_body_model(cfg.body), load_robot(cfg.robot)
    a = store.read("shape_fit", manifest["shared"]["shape_fit"])
    fit = ShapeFit.from_arrays(a.arrays, a.attrs)
    sids = sorted(s for s, v in manifest["sequences"].items() if v["status"] == "ok")[: args.limit]
    rows, cpu = [], 0.0
    for sid in sids:
        steps = manifest["sequences"][sid]["steps"]
        a = store.read("collide", steps["collide"])
        motion = CollisionResult.from_arrays(a.arrays, a.attrs).motion
        a = store.read("retarget", steps["retarget"])
        ik_only = IKSolution.from_arrays(a.arrays, a.attrs)
        a = store.read("refine", steps["refine"])
        old = RefineResult.from_arrays(a.arrays, a.attrs)
        targets = build_targets(motion, body, fit, robot, cfg.ik)
        t0 = time.process_time()
        new = refine(motion, body, fit, robot, targets, ik_only, cfg.critic, cfg.ik, cfg.render)
        cpu += time.process_time() - t0
        m_old, m_new = old.final.metrics, new.final.metrics
        rows.append({"accepted_before": old.accepted, "accepted_after": new.accepted,
                     "loc_before": m_old["location_err"], "loc_after": m_new["location_err"],
                     "palm_before": m_old["palm_deg"], "palm_after": m_new["palm_deg"],
                     "rounds_before": len(old.rounds) - 1, "rounds_after": len(new.rounds) - 1})
        print(f"{sid} before: accepted={old.accepted} round {old.final.index} "
              f"loc={m_old['location_err']:.4f} palm={m_old['palm_deg']:.2f} | after: "
              f"accepted={new.accepted} round {new.final.index} loc={m_new['location_err']:.4f} "
              f"palm={m_new['palm_deg']:.2f} ({len(new.rounds) - 1} re-solves)", flush=True)
        if args.rounds_detail:
            for r in new.rounds:
                act = r.action or {}
                prims = [(p["name"], p["amount"]) for p in act.get("primitives_positions", [])
                         + act.get("primitives_orientation", [])]
                print(f"    round {r.index}: loc={r.metrics['location_err']:.4f} "
                      f"palm={r.metrics['palm_deg']:.2f} {act.get('verdict')} {prims} | {act.get('reason', '')}")
    mean = lambda k: float(np.mean([r[k] for r in rows]))  # noqa: E731
    print(f"RESULT run={args.run} n={len(rows)} "
          f"accepted_before={sum(r['accepted_before'] for r in rows)} "
          f"accepted_after={sum(r['accepted_after'] for r in rows)} "
          f"location_err_before={mean('loc_before'):.4f} location_err_after={mean('loc_after'):.4f} "
          f"palm_deg_before={mean('palm_before'):.2f} palm_deg_after={mean('palm_after'):.2f} "
          f"rounds_before={mean('rounds_before'):.2f} rounds_after={mean('rounds_after'):.2f} "
          f"refine_cpu_s_per_seq={cpu / max(len(rows), 1):.2f}")


if __name__ == "__main__":
    main()
