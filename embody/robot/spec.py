"""The typed robot definition read from `configs/robots/<name>.yaml`."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from embody.errors import ConfigError


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class MjcfSource(_Strict):
    #: Explicit MJCF path (absolute, or relative to the YAML file); tried first.
    path: str | None = None
    #: Path inside the MuJoCo Menagerie tree (offline wheel first, then `mujoco-menagerie`).
    file: str | None = None


class LinkRef(_Strict):
    """A point on a robot body: the body's origin plus `offset` in the body frame."""

    body: str
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


class IgnoredPair(_Strict):
    """A body pair whose contacts are not self-collision, with why (checked at load,
    `embody.robot.exclusions`)."""

    bodies: tuple[str, str]
    #: joint: a joint's two links (parent and child; MuJoCo never reports them);
    #: always: in contact at every pose of the joints between them (sampled at load).
    kind: Literal["joint", "always"]
    reason: str = Field(min_length=1)
    #: Measured penetration (mm) of the pair's collision geoms at rest (range over the sampled
    #: poses where it varies), for the record.
    depth_mm: float | tuple[float, float] | None = None


class CollisionSpec(_Strict):
    geom_groups: list[int] = [3]
    #: Every excluded body pair, each with its kind and reason: nothing else is left out, fingers
    #: of one hand included.
    ignore_pairs: list[IgnoredPair] = []


class ProxySpec(_Strict):
    """A collision proxy fitted to the collision geoms of `bodies` (fnmatch patterns)."""

    bodies: list[str]
    #: Indices into the matched collision geoms (all when empty).
    geoms: list[int] = []
    #: Spheres of a chain/cluster, or surface points per geom of `points`.
    spheres: int = Field(3, ge=1, le=64)
    #: chain: spheres along the principal axis (limbs); cluster: k-means cover (bulky parts);
    #: points: hull surface points per geom (radius 0); hull: each geom's convex polytope.
    layout: Literal["chain", "cluster", "points", "hull"] = "chain"
    #: Most planes per geom polytope (`hull`).
    planes: int = Field(48, ge=4, le=512)
    #: Fraction of the points each sphere must cover (radius percentile): 1 = conservative.
    cover: float = Field(0.9, gt=0.0, le=1.0)


class GainGroup(_Strict):
    """PD gains and command rate of the motors of a group of joints, and where they come from."""

    #: fnmatch patterns over joint names; the first group that matches a joint owns it.
    joints: list[str]
    kp: float = Field(gt=0.0)  # N·m/rad
    kd: float = Field(ge=0.0)  # N·m·s/rad
    #: How often the robot stack sends this group a new command (q, q̇, τ_ff, kp, kd).
    rate_hz: float = Field(gt=0.0, le=10000.0)
    #: Citation of the numbers (project, file, what they are used for there).
    source: str = Field(min_length=1)


class StanceSpec(_Strict):
    """How the standing replay holds the legs: stiff joint PD toward the stance pose (plus the
    feed-forward of the feet carrying the body), so the robot stands as one rigid body on its
    feet and standing tests the ZMP of the motion, not a balance policy."""

    kp: float = Field(gt=0.0)
    kd: float = Field(ge=0.0)
    #: Leg joint values of the stance where the MJCF has no `stand` keyframe (others: 0).
    pose: dict[str, float] = {}
    source: str = Field(min_length=1)


class ActuationSpec(_Strict):
    """Motor control of the robot for physics replay and export (effort limits: the MJCF)."""

    groups: dict[str, GainGroup]
    stance: StanceSpec | None = None


class RobotSpec(_Strict):
    mjcf: MjcfSource
    root_body: str
    torso_body: str
    links: dict[str, LinkRef]
    fit_weights: dict[str, float] = {}
    tpose: dict[str, float] = {}
    #: IK start and posture prior (joints not named: 0). Zero is arms down, forearms forward on
    #: G1/H1: close to a signer's neutral pose, unlike the T-pose.
    rest: dict[str, float] = {}
    ik_joints: list[str]
    #: IK joints that bend the torso (fnmatch): a stronger posture prior keeps them near rest.
    waist_joints: list[str] = []
    hands: dict[str, dict[str, list[str]]] = {}
    velocity_limits: dict[str, float] = {"*": 5.0}
    #: `ik` config values for this robot (e.g. a robot without wrist joints weights wrist
    #: rotation differently): applied over the defaults, under the user's files and --set
    #: (`embody.config.load_config`), so they are part of every robot step's key.
    ik: dict[str, Any] = {}
    collision: CollisionSpec = CollisionSpec()
    proxies: dict[str, ProxySpec] = {}
    proxy_pairs: list[tuple[str, str]] = []
    #: Named surface points (`embody.body.landmarks` names) for sign fidelity; a hand without
    #: fingers has only wrist and palm.
    landmarks: dict[str, LinkRef] = {}
    #: Per side, the palm normal (palms down at the T-pose) as a unit `offset` direction in `body`.
    palm_normals: dict[str, LinkRef] = {}
    #: PD gains and command rates per joint group (physics replay, export); None: not given.
    actuation: ActuationSpec | None = None


def read_spec(path: Path) -> RobotSpec:
    """Parse and validate a robot YAML; every error names `<file>:<dotted key>`."""
    from embody.config.yamlload import YAMLBudgetError, load_yaml

    try:
        data = load_yaml(Path(path).read_text())
    except OSError as exc:
        raise ConfigError(str(path), f"cannot read robot definition: {exc.strerror or exc}") from None
    except YAMLBudgetError as exc:
        raise ConfigError(str(path), f"refused: {exc}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(str(path), f"not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(str(path), "robot definition must be a mapping")
    try:
        spec = RobotSpec.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        key = ".".join(str(p) for p in err["loc"]) or "<root>"
        msg = "unknown key" if err["type"] == "extra_forbidden" else err["msg"]
        raise ConfigError(f"{path}:{key}", msg) from None
    for side in ("left_wrist", "right_wrist"):
        if side not in spec.links:
            raise ConfigError(f"{path}:links.{side}", "required link mapping missing")
    for a, b in spec.proxy_pairs:
        for name in (a, b):
            if name not in spec.proxies:
                raise ConfigError(f"{path}:proxy_pairs", f"unknown proxy {name!r}")
    return spec
