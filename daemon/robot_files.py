"""Robot model files: read the YAML, hand the mapping to the solvers' validator."""
from __future__ import annotations

from importlib import resources
from pathlib import Path

import re

import yaml

from ..solvers.robot_model import KinematicModel, ModelError, model_from_mapping
from ..solvers.tree_model import tree_from_mapping


class _StrictLoader(yaml.SafeLoader):
    """Safe YAML with two fixes for hand-written model files: ``1e3`` is a number
    (as in YAML 1.2, not a string as in 1.1) and a repeated key is an error
    instead of silently overriding the first."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise ModelError(f"{self.name}:{key_node.start_mark.line + 1}: {key}: "
                                 "key given twice in the same mapping")
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


_StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+$"),
    list("-+0123456789."),
)


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


def read_yaml(path: Path, error: type[Exception] = ModelError):
    """Read a hand-written YAML file strictly (see _StrictLoader); every problem is one
    `error` whose message starts with the file (and line, where YAML knows it)."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{path}: cannot read: {exc}") from None
    loader = _StrictLoader(text)
    loader.name = str(path)
    try:
        return loader.get_single_data()
    except ModelError as exc:  # a repeated key
        raise error(str(exc)) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f":{mark.line + 1}" if mark is not None else ""
        raise error(f"{path}{where}: not valid YAML: {getattr(exc, 'problem', exc)}") from None
    finally:
        loader.dispose()


def load_robot(name_or_path: str | Path) -> KinematicModel:
    """Load and validate a robot model; raises ModelError naming file and key."""
    path = resolve_robot(str(name_or_path))
    doc = read_yaml(path)
    if isinstance(doc, dict) and "branches" in doc:
        return tree_from_mapping(doc, source=str(path))
    return model_from_mapping(doc, source=str(path))
