"""What the report's numbers mean: metric definitions, verdicts and the paper it follows.

One source for the HTML page and the README excerpt (`scripts/readme_tables.py`), so the
definitions a reader sees next to a table are the ones the README prints.
"""

from __future__ import annotations

from embody.verdicts import VERDICTS

__all__ = ["COLLISION_MODEL", "COLUMNS", "METRICS", "PAPER", "ROBOT_NOTES", "VERDICT_DEFINITIONS",
           "paper_bibtex", "paper_citation", "robot_note"]

#: The paper whose tables these are (the project's issue 36 names it).
PAPER = {
    "key": "khan2026sign",
    "title": "From Sign Language Generation to Humanoid Execution: Vision–Language Guided "
             "Retargeting with Collision Mitigation",
    "authors": ("N. Khan", "B. Wu", "R. Shi", "B. Yen", "T. Ashizawa", "C. T. Ishi", "T. Minato",
                "K. Nakadai"),
    "venue": "IEEE/RSJ International Conference on Intelligent Robots and Systems (IROS)",
    "year": 2026,
}

#: The volumetric body model whose self-collision loss the paper uses (title and venue checked).
COLLISION_MODEL = ("VolumetricSMPL: A Neural Volumetric Body Model for Efficient Interactions, "
                   "Contacts, and Collisions (Mihajlovic et al., ICCV 2025)")

#: Table column / row name → definition.
METRICS = (
    ("Collision energy", "volumetric self-collision energy L_col (Eq. 1): mean over frames of the "
     "squared depths of body vertices inside other body parts' convex volumes; statistics over "
     "the sequences that collided before mitigation."),
    ("Improved sequences", "colliding sequences whose energy went down (n/N and %); sequences with "
     "zero energy before count as \"no collision\", neither success nor failure."),
    ("Collision reduction", "(before − after) / before × 100 per sequence, then median or mean."),
    ("Pose MSE vs. original", "mean over frames of the squared norm of the pose change "
     "(axis-angle, all joints); median over sequences."),
    ("ΔAccel MSE", "mean squared second difference of the pose after minus before: the jerkiness "
     "the optimisation added (negative = smoother); median over sequences."),
    ("Runtime per sequence", "wall-clock seconds of the collision optimisation, mean."),
    ("Paper (reported)", "the paper's own figures for comparison; blank where it reports none."),
    ("Table II", "the same metrics per loss setting: N colliding sequences, Succ. = improved %, "
     "Red. = median reduction %, medians of Pose/ΔAccel MSE, mean time."),
    ("Wrist pos. mean / p95", "distance between robot and human wrists in the robot torso frame "
     "(mm), both wrists, mean and 95th percentile over frames, averaged over sequences."),
    ("Wrist rot. mean", "geodesic angle between robot and human wrist orientations (deg)."),
    ("DTW wrist", "wrist distance after dynamic time warping (mm): robust to timing drift."),
    ("Limit viol. / Vel. viol.", "(frame, joint) samples outside the joint position / velocity "
     "limits, summed over sequences (target 0)."),
    ("Self-coll. frames", "frames with a penetrating MuJoCo contact between non-adjacent robot "
     "bodies, summed over sequences (target 0)."),
    ("Rounds / Accepted", "critic rounds used (mean) and the share of sequences it accepted."),
    ("IK only / Location-preserving / Refined", "Table III rows: IK on shape-fit targets; IK on "
     "targets anchored to the robot's own landmarks (the run's retarget step); after the "
     "critic's rounds."),
    ("Location err.", "each hand's palm centre relative to the human hand's nearest face or "
     "trunk landmark, in the torso frame, divided by each body's scale (shoulder width); the "
     "error is the distance between the human's and the robot's vectors, mean over frames and "
     "hands (scale units; mm = scale × the robot's shoulder width). Measured against the human "
     "after collision mitigation, not against the IK targets."),
    ("Location agree", "of the frames where the human hand is within 0.5 body scales of a "
     "landmark, the share where the robot hand's nearest landmark is the same one, counting a "
     "tie (either hand within `fidelity.location_tie` = 0.05 scales as near to the other's "
     "choice: face landmarks are 1.5-4 cm apart) as agreement (%); sequences.csv also carries "
     "the exact figure (`location_agree_exact_pct`)."),
    ("Palm orient.", "angle between the human's and the robot's palm normals, each in its own "
     "torso frame (deg)."),
    ("Handshape err.", "per finger the robot has, the difference of normalised flexion "
     "(fingertip-to-palm distance over finger length), mean; blank for a robot without fingers."),
    ("Movement DTW", "dynamic-time-warped distance between the normalised palm paths (scale "
     "units)."),
    ("Table III (physics)", "the final trajectory's exported 50 Hz array replayed in MuJoCo "
     "(`embody.physics`): each motor applies clip(kp (q_ref − q) + kd (q̇_ref − q̇) + τ_ff, effort "
     "limit) at the robot's control rate, q_ref a cubic Hermite spline of the samples, τ_ff their "
     "fixed-base inverse dynamics; gains, rates and their sources in the robot YAML's `actuation`, "
     "effort limits from the MJCF. Torque > limit: samples of the exported array whose inverse "
     "dynamics asks any joint for more than its limit (summed); Peak torque/limit: the largest such "
     "ratio; Saturated steps: control steps (pelvis welded) where any motor hits its limit; Palm "
     "p95 sim.: simulated vs. reference palm positions (mm, p95 per sequence, mean); Sim. "
     "self-contacts: samples of the simulated motion with counted geoms > 1 mm into each other; "
     "ZMP margin min: cart-table ZMP of the robot standing (legs at the stance) inside its feet's "
     "support polygon (mm, negative = outside); Stays up standing: the standing replay (free base on "
     "the floor, legs under a stiff PD toward the stance with the feet carrying the body as "
     "feed-forward) keeps the pelvis within 10° tilt, 50 mm drift and 50 mm drop and the feet flat "
     "(≤ 5° tilt, ≤ 5 mm lift); Location err. sim.: sign location error of the simulated motion "
     "against the human."),
    ("Contact F1", "hand-hand, hand-face and hand-chest contact frames of the human (surfaces "
     "within ε) recovered on the robot (MuJoCo geometry distances; a penetrating contact does "
     "not count), pooled over sequences."),
)

#: What a robot can and cannot express, printed under Table III for runs of that robot.
ROBOT_NOTES = {
    "unitree_g1_dex3": (
        "Unitree G1 with Dex3 hands: 7-DoF arms with 3 wrist joints, so wrist position and "
        "orientation are both tracked; each hand has a thumb, an index and a middle finger "
        "(ring and pinky are mapped onto the middle finger)."),
    "unitree_h1": (
        "Unitree H1: 4-DoF arms (shoulder pitch, roll, yaw and elbow), no wrist joints and no "
        "hands; its 'wrist' is a point at the end of the forearm. Three of the four joints "
        "place that point anywhere within the arm's reach; the fourth is the elbow's swivel "
        "about the shoulder-wrist line, the only freedom left for the hand's orientation, "
        "which is the forearm's. The palm cannot bend, tilt or turn on its own, so wrist "
        "rotation and palm orientation errors stay large by construction (not a tracking "
        "failure), handshape is blank (no fingers), and location and contacts are measured "
        "with the palm point at the end of the forearm."),
}


def robot_note(robot: str) -> str:
    """What `robot` can and cannot express (blank for a robot without a note)."""
    return ROBOT_NOTES.get(robot, "")

#: The verdicts, as the first table names them.
VERDICT_DEFINITIONS = (
    ("Processed ok", VERDICTS["processed_ok"] + "."),
    ("Export-valid", VERDICTS["export_valid"] + "."),
    ("Critic-accepted", VERDICTS["critic_accepted"] + "."),
    ("Physics-valid", VERDICTS["physics_valid"] + "."),
)

#: The per-sequence table's columns: header → (sequences.csv column, definition).
COLUMNS = {
    "Wrist err. (mm)": ("retarget.wrist_pos_err_mm",
                        "IK-only wrist position error against the human wrists, mean (mm)"),
    "Wrist rot. (deg)": ("retarget.wrist_rot_err_deg",
                         "IK-only wrist orientation error, mean (deg)"),
    "Location err. (mm)": ("final.location_err_mm",
                           "final trajectory: mean distance between the human's and the robot's "
                           "palm offsets from the human hand's nearest landmark (body-scale "
                           "normalised, shown in the robot's mm); per frame in the location plot"),
    "Location agree (%)": ("final.location_agree_pct",
                           "final trajectory: frames near a landmark whose nearest landmark is "
                           "the same on the robot (%)"),
    "Palm orient. (deg)": ("final.palm_deg", "final trajectory: palm-normal angle error (deg)"),
    "Self-coll. frames": ("metrics.self_collision_frames",
                          "MuJoCo self-collision frames of the final trajectory"),
    "Coll. red. (%)": ("collide.reduction_pct",
                       "SMPL-X collision energy reduction of the mitigation step (%)"),
}


def paper_citation() -> str:
    """The paper as a reference list prints it: authors, “title,” venue, year."""
    authors = ", ".join(PAPER["authors"][:-1]) + ", and " + PAPER["authors"][-1]
    return f"{authors}, “{PAPER['title']},” in {PAPER['venue']}, {PAPER['year']}."


def paper_bibtex() -> str:
    """The paper as a BibTeX `@inproceedings` entry (ASCII, so pdflatex needs no unicode setup)."""
    title = PAPER["title"].replace("–", "--")
    authors = " and ".join(PAPER["authors"])
    return (f"@inproceedings{{{PAPER['key']},\n"
            f"  author    = {{{authors}}},\n"
            f"  title     = {{{{{title}}}}},\n"
            f"  booktitle = {{{PAPER['venue']}}},\n"
            f"  year      = {{{PAPER['year']}}},\n"
            f"}}\n")
