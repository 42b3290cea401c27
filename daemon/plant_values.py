"""What the plant is told of the cell: the service's state and run dicts turned into the plain
values a plant interface publishes (daemon/plant_opcua.py serves them over OPC UA).

Kept apart from any protocol, and tolerant: the dicts come from the service (its status, the
JSON API's run dict) and a value that is missing or of another type becomes None (a
coordinate NaN), never an exception and never an invented number. The evaluation is the two
words of OPC 40001-101 (OPC UA for Machinery, Result Transfer): ``OK`` or ``NOK``.
"""
from __future__ import annotations

import math
import re
from datetime import datetime, timezone

TEXT_LIMIT = 256  # characters of any text published
OK_VERDICTS = ("ok", "corrected")  # a check's verdicts that mean the tool is where the controller thinks
CELL_NAMES = ("State", "Health", "MountedTool", "RunUnderWay")
# LastResult's tool frame: its names, and the keys of the run's result["tool_frame"] (mm, degrees)
FRAME_VARIABLES = (("X_mm", "x_mm"), ("Y_mm", "y_mm"), ("Z_mm", "z_mm"), ("Rx_deg", "rx_deg"),
                   ("Ry_deg", "ry_deg"), ("Rz_deg", "rz_deg"))
RESULT_NAMES = ("RunId", "Routine", "ToolId", "Verdict", "Evaluation", "ResultCode", "ResultName",
                *(name for name, _ in FRAME_VARIABLES), "PassedGates", "WrittenBack", "FinishedAt")


def _int(value, bits: int = 64) -> int | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    if isinstance(value, float) and not (math.isfinite(value) and value.is_integer()):
        return None
    value = int(value)
    return value if -(1 << (bits - 1)) <= value < (1 << (bits - 1)) else None


def _float(value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return math.nan
    return float(value)


def text(value) -> str | None:
    if value is None or isinstance(value, (dict, list, tuple, set)):
        return None
    return str(value)[:TEXT_LIMIT]


def _bool(value) -> bool | None:
    return value if isinstance(value, bool) else None


def _time(epoch_s) -> datetime | None:
    seconds = _float(epoch_s)
    try:
        return datetime.fromtimestamp(seconds, timezone.utc) if math.isfinite(seconds) else None
    except (OverflowError, OSError, ValueError):
        return None


def evaluation(run: dict) -> str:
    """``OK`` or ``NOK`` for a run that has been published: OK when a check's verdict is ok or
    corrected, or when a calibration (no verdict) passed every gate with result code 0."""
    verdict = text(run.get("verdict"))
    if verdict is not None:
        return "OK" if verdict in OK_VERDICTS else "NOK"
    return "OK" if run.get("passed_gates") is True and _int(run.get("result_code")) == 0 else "NOK"


def state_values(state: dict) -> tuple[dict, dict]:
    """The Cell values of a state dict (``state``, ``health``, ``mounted_tool``, ``run``,
    ``devices``) and its devices {name: text}; what is missing or of another type is None. The
    service's own status shapes are taken too: health as {"level", ...}, the mounted tool as
    {"id", ...}, the run under way as ``run_id``."""
    state = state if isinstance(state, dict) else {}
    health, tool = state.get("health"), state.get("mounted_tool")
    health = health.get("level") if isinstance(health, dict) else health
    tool = tool.get("id") if isinstance(tool, dict) else tool
    run = state.get("run", state.get("run_id"))  # the service's status says run_id
    values = {"State": text(state.get("state")), "Health": text(health), "MountedTool": _int(tool, 32),
              "RunUnderWay": _int(run)}
    devices = state.get("devices")
    devices = {} if not isinstance(devices, dict) else {
        browse_name(name): text(said) for name, said in devices.items() if browse_name(name)}
    return values, devices


def browse_name(name) -> str:
    """A name as the plant reads it in a node's name: letters, digits, ``_.-`` (anything else
    dropped), at most 64 characters."""
    return re.sub(r"[^A-Za-z0-9_.\-]", "", str(name))[:64]


def result_values(run: dict) -> dict:
    """The LastResult values of a run dict (the JSON API's /api/v1/runs/<id>); what is missing
    or of another type is None, a missing coordinate NaN."""
    run = run if isinstance(run, dict) else {}
    result = run.get("result")
    frame = result.get("tool_frame") if isinstance(result, dict) else None
    frame = frame if isinstance(frame, dict) else {}
    return {"RunId": _int(run.get("id")), "Routine": text(run.get("routine")), "ToolId": _int(run.get("tool_id"), 32),
            "Verdict": text(run.get("verdict")), "Evaluation": evaluation(run),
            "ResultCode": _int(run.get("result_code"), 32), "ResultName": text(run.get("result_name")),
            **{name: _float(frame.get(key)) for name, key in FRAME_VARIABLES},
            "PassedGates": _bool(run.get("passed_gates")), "WrittenBack": _bool(run.get("written_back")),
            "FinishedAt": _time(run.get("finished_at"))}


EMPTY_RESULT = {**{name: None for name in RESULT_NAMES}, "Evaluation": "",
                **{name: math.nan for name, _ in FRAME_VARIABLES}}
