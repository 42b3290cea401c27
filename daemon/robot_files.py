"""Robot model files: read the YAML, hand the mapping to the solvers' validator."""
from __future__ import annotations

from importlib import resources
from pathlib import Path

import yaml

from ..solvers.robot_model import KinematicModel, ModelError, model_from_mapping


def shipped_robots() -> dict[str, Path]:
    """Robot models that ship with cellcal, by file stem (e.g. ``ur10e``)."""
    folder = resources.files("cellcal.config") / "robots"
    return {Path(str(p)).stem: Path(str(p)) for p in folder.iterdir() if str(p).endswith(".yaml")}


def resolve_robot(name_or_path: str) -> Path:
    """A path as given, or the name of a shipped model (``ur10e``)."""
    path = Path(name_or_path)
    if path.exists() or path.suffix in (".yaml", ".yml") or "/" in name_or_path:
        return path
    shipped = shipped_robots()
    if name_or_path in shipped:
        return shipped[name_or_path]
    raise ModelError(f"{name_or_path}: no such file, and not a shipped robot "
                     f"(shipped: {', '.join(sorted(shipped))})")


def load_robot(name_or_path: str | Path) -> KinematicModel:
    """Load and validate a robot model; raises ModelError naming file and key."""
    path = resolve_robot(str(name_or_path))
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ModelError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ModelError(f"{path}: cannot read: {exc}") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f":{mark.line + 1}" if mark is not None else ""
        raise ModelError(f"{path}{where}: not valid YAML: {getattr(exc, 'problem', exc)}") from None
    return model_from_mapping(doc, source=str(path))
