"""Typed configuration: `configs/default.yaml` + `--config FILE` + `--set section.key=value`.

Every error names the dotted key and is a `ConfigError` (exit 2 in the CLI).
"""

from __future__ import annotations

import copy
import reprlib
import os
from pathlib import Path
from typing import Any, Iterable

import yaml
from pydantic import ValidationError

from embody.config.base import Section, canonical_json
from embody.config.body import BodyConfig
from embody.config.collision import CollisionConfig
from embody.config.critic import CriticConfig
from embody.config.fidelity import FidelityConfig
from embody.config.ik import IKConfig
from embody.config.io import IOConfig
from embody.config.render import RenderConfig
from embody.config.robot import RobotConfig
from embody.config.run import DebugConfig, RunConfig
from embody.config.yamlload import YAMLBudgetError, load_yaml
from embody.errors import ConfigError

__all__ = ["Config", "Section", "canonical_json", "load_config", "configs_dir", "parse_set"]


class Config(Section):
    io: IOConfig = IOConfig()
    body: BodyConfig = BodyConfig()
    collision: CollisionConfig = CollisionConfig()
    robot: RobotConfig = RobotConfig()
    ik: IKConfig = IKConfig()
    render: RenderConfig = RenderConfig()
    critic: CriticConfig = CriticConfig()
    fidelity: FidelityConfig = FidelityConfig()
    run: RunConfig = RunConfig()
    debug: DebugConfig = DebugConfig()

    def section_json(self, name: str) -> str:
        """Canonical JSON of one section: what that step's content key hashes."""
        return canonical_json(getattr(self, name))


def configs_dir() -> Path:
    """Where `configs/` lives: `$EMBODY_CONFIGS`, else `embody/configs` (a symlink to the
    top-level `configs/` in a checkout, a packaged copy in a wheel)."""
    if "EMBODY_CONFIGS" in os.environ:
        return Path(os.environ["EMBODY_CONFIGS"])
    return Path(__file__).resolve().parents[1] / "configs"


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(str(path), f"cannot read config file: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(str(path), f"not UTF-8 text (byte {exc.start})") from None
    try:
        data = load_yaml(text) or {}
    except YAMLBudgetError as exc:
        raise ConfigError(str(path), f"refused: {exc}") from None
    except yaml.YAMLError as exc:
        # PyYAML's message spans several lines with a caret; errors here are one line.
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(str(path), f"not valid YAML{where}: {problem}") from None
    if not isinstance(data, dict):
        raise ConfigError(str(path), "top level must be a mapping of sections")
    # `section:` with nothing under it reads as None: it means "this section's defaults".
    return {key: value for key, value in data.items() if value is not None}


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def parse_set(item: str) -> dict[str, Any]:
    """`section.key=value` → nested dict; the value is parsed as YAML (numbers, lists, ...)."""
    if "=" not in item:
        raise ConfigError(item, "--set expects section.key=value")
    dotted, raw = item.split("=", 1)
    parts = [p for p in dotted.strip().split(".") if p]
    if len(parts) < 2:
        raise ConfigError(dotted, "--set key must be section.key")
    try:
        value = load_yaml(raw)
    except YAMLBudgetError as exc:
        raise ConfigError(dotted, f"--set value refused: {exc}") from None
    except yaml.YAMLError:
        value = raw
    nested: dict[str, Any] = {parts[-1]: value}
    for part in reversed(parts[:-1]):
        nested = {part: nested}
    return nested


def _robot_ik(data: dict[str, Any]) -> dict[str, Any]:
    """The robot definition's own `ik:` values ({"ik": {...}}), read from its YAML (no robot
    model is built); {} when the robot file is missing or has none (loading it reports that)."""
    robot = data.get("robot") or {}
    if not isinstance(robot, dict) or not isinstance(robot.get("name"), str):
        return {}
    root = Path(robot["robots_dir"]) if robot.get("robots_dir") else configs_dir() / "robots"
    path = root / f"{robot['name']}.yaml"
    try:
        ik = _read_yaml(path).get("ik") if path.is_file() else None
    except Exception:  # a broken robot file is reported where the robot loads
        return {}
    return {"ik": ik} if isinstance(ik, dict) else {}


def load_config(
    files: Iterable[str | Path] = (),
    sets: Iterable[str] = (),
    *,
    defaults: str | Path | None = None,
) -> Config:
    """Load defaults, then each file, then each `--set`, validating once at the end."""
    default_path = Path(defaults) if defaults is not None else configs_dir() / "default.yaml"
    data: dict[str, Any] = _read_yaml(default_path) if default_path.exists() else {}
    user: dict[str, Any] = {}
    for f in files:
        user = _merge(user, _read_yaml(Path(f)))
    for item in sets:
        user = _merge(user, parse_set(item))
    data = _merge(_merge(data, _robot_ik(_merge(data, user))), user)
    try:
        return Config.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        key = ".".join(str(p) for p in err["loc"]) or "<root>"
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        extra = f" ({len(exc.errors()) - 1} more)" if len(exc.errors()) > 1 else ""
        raise ConfigError(key, f"{msg}; got {shown(err.get('input'))}{extra}") from None


def shown(value: Any, limit: int = 120) -> str:
    """`repr(value)` cut to `limit` characters: an error line quotes the value, never a whole
    document (a list of a million items is one line of a few dozen characters)."""
    short = reprlib.Repr()
    short.maxlevel, short.maxlist, short.maxdict = 3, 6, 6
    short.maxstring = short.maxother = limit
    text = short.repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."

