"""Cell files changed for a test through their YAML, not through their text.

    edited_cell(tmp_path, "sim-net", {"drivers": {"panel": {"timeout_s": 0.3}}}, host=host)

loads the shipped cell file (or a path) as cellcal reads it, deep-merges the changes into
it and writes it to ``tmp_path/name``; the path is returned. A change that names a key the
file does not have adds it, so a misspelt key stays a key the cell file refuses (the
negative tests rely on it) and a key the file renamed shows as that refusal instead of a
text replacement that silently did nothing.

In `changes`: a mapping merges into the mapping it meets; a mapping with integer keys edits
those items of a list (``{"beams": {1: {"radius_m": -0.001}}}``); :data:`DELETE` removes
the key; :func:`replaced` puts its value in place of what was there (a whole section);
anything else replaces the value. `changes` may also be a function that edits the loaded
document in place (renaming a key, say). ``host=`` points every networked driver at another
address first, as :meth:`Cell.on_host` does for a loaded cell.
"""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import yaml

from cellcal.config.cell_files import shipped_cells
from cellcal.config.cells import CellFileError
from cellcal.config.reader import read_yaml

DELETE = object()


class replaced:  # noqa: N801 (used like a function)
    """``{"tracker": replaced({...})}``: the whole value, not merged into the old one."""

    def __init__(self, value):
        self.value = value


def cell_document(base: str | Path) -> dict:
    """A cell file's YAML as cellcal reads it (strictly: ``1e3`` is a number), by name or path."""
    shipped = shipped_cells()
    return read_yaml(shipped[base] if isinstance(base, str) and base in shipped else Path(base), CellFileError)


def merged(into, changes):
    """`into` with `changes` deep-merged (see the module's doc); `into` itself is left as it was."""
    if isinstance(changes, replaced):
        return copy.deepcopy(changes.value)
    if isinstance(changes, dict) and isinstance(into, list) and all(isinstance(k, int) for k in changes):
        out = list(into)
        for k, change in changes.items():
            out[k] = merged(out[k], change)
        return out
    if isinstance(changes, dict) and isinstance(into, dict):
        out = dict(into)
        for key, change in changes.items():
            if change is DELETE:
                del out[key]
            else:
                out[key] = merged(out[key], change) if key in out else merged(None, change)
        return out
    if isinstance(changes, dict):  # a new section or mapping
        return {key: merged(None, change) for key, change in changes.items() if change is not DELETE}
    return copy.deepcopy(changes)


def on_host(document: dict, host: str) -> dict:
    """The document with every networked driver (``host:`` option) at `host`, and the daemon's
    status page there too (each test cell's daemon serves on its own address: no port shared
    between parallel tests)."""
    doc = copy.deepcopy(document)
    specs = list((doc.get("drivers") or {}).values())
    specs += [robot.get("driver") for robot in (doc.get("robots") or {}).values()]
    for spec in specs:
        if isinstance(spec, dict) and "host" in spec:
            spec["host"] = host
    doc["status_page"] = {**(doc.get("status_page") or {}), "host": host}
    return doc


def _plain(value):
    """numpy values as the Python numbers and lists YAML writes."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


class _Dumper(yaml.SafeDumper):
    """Sections as blocks, lists of numbers or names on one line, as the shipped files are written."""

    def represent_list(self, data):
        flat = all(not isinstance(v, (dict, list)) for v in data)
        return self.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flat)


_Dumper.add_representer(list, _Dumper.represent_list)


def edited_cell(folder: Path, base: str | Path, changes=None, *, name: str = "cell.yaml",
                host: str | None = None) -> Path:
    """`base` (a shipped cell's name or a path) with `changes`, written to ``folder/name``."""
    doc = cell_document(base)
    if host is not None:
        doc = on_host(doc, host)
    if callable(changes):
        changes(doc)
    elif changes is not None:
        doc = merged(doc, changes)
    path = Path(folder) / name
    path.write_text(yaml.dump(_plain(doc), Dumper=_Dumper, sort_keys=False, default_flow_style=False, width=1000))
    return path
