"""The status page's headline (daemon/service.py ``health``): the state with what needs attention
beside it, and a level the page colours by. A green "idle" only when nothing needs attention."""
from __future__ import annotations

import pytest

from cellcal.daemon.service import health

GOOD = {"robot": "ready", "panel": "ok", "trigger": "open"}


def ended(state: str, code: int, name: str, run_id: int = 7) -> dict:
    return {"id": run_id, "routine": "tcp-check", "state": state, "result_code": code, "result": name,
            "reason": "...", "verdict": None, "at": 0.0, "fault_lamp": state in ("fault", "refused", "interrupted")}


def test_the_robot_states_named_are_the_ones_the_service_records():
    """seen["robot"] holds RobotState's values: the names health() knows must be those."""
    from cellcal.daemon.service import ROBOT_FAULTS
    from cellcal.drivers.interfaces import RobotState

    assert set(ROBOT_FAULTS) <= {s.value for s in RobotState} and RobotState.READY.value == "ready"


def test_idle_with_everything_answering_and_a_good_last_run_is_ok():
    assert health("idle", False, ended("done", 0, "OK"), GOOD, None, None) == {"level": "ok", "says": "idle"}
    assert health("idle", False, None, GOOD, None, None) == {"level": "ok", "says": "idle"}  # no run yet


@pytest.mark.parametrize("devices, level, says", [
    ({**GOOD, "robot": "disconnected"}, "fault", "idle; robot disconnected"),
    ({**GOOD, "robot": "protective stop"}, "fault", "idle; robot protective stop"),
    ({**GOOD, "robot": "emergency stop"}, "fault", "idle; robot emergency stop"),
    ({**GOOD, "robot": "reconnecting"}, "attention", "idle; robot reconnecting"),
    ({**GOOD, "robot": "program running"}, "attention", "idle; robot program running"),
    ({**GOOD, "robot": "unknown"}, "attention", "idle; robot unknown"),
    ({**GOOD, "panel": "lost"}, "attention", "idle; panel lost"),
    ({**GOOD, "robot": "disconnected", "panel": "lost"}, "fault", "idle; robot disconnected; panel lost"),
])
def test_a_device_that_is_not_well_is_in_the_headline_and_never_green(devices, level, says):
    assert health("idle", False, ended("done", 0, "OK"), devices, None, None) == {"level": level, "says": says}


@pytest.mark.parametrize("state, code, name", [("interrupted", 41, "INTERRUPTED"), ("fault", 33, "CHECK_ALARM"),
                                               ("refused", 15, "CALIBRATE_FIRST")])
def test_a_last_run_that_lit_the_fault_lamp_is_a_fault_naming_it(state, code, name):
    got = health("idle", False, ended(state, code, name), GOOD, None, None)
    assert got == {"level": "fault", "says": f"idle; the last run (7, tcp-check) ended {state}: {code} {name}"}


def test_an_aborted_run_lights_no_fault_lamp():
    assert health("idle", False, ended("aborted", 40, "ABORTED"), GOOD, None, None)["level"] == "ok"


def test_a_run_under_way_is_running_or_waiting_for_the_operator_and_keeps_device_trouble_beside_it():
    assert health("solving", True, ended("fault", 33, "CHECK_ALARM"), GOOD, None, None) == \
        {"level": "running", "says": "running: solving"}  # the previous run's fault is not this run's
    waiting = {"message": "move the plate to placement p2", "step": 2, "until": 0.0, "time_left_s": 30.0}
    assert health("running", True, None, {**GOOD, "panel": "lost"}, waiting, None) == \
        {"level": "waiting", "says": "waiting for the operator: move the plate to placement p2; panel lost"}


def test_a_frame_still_owed_to_the_controller_needs_attention():
    got = health("idle", False, None, GOOD, None, 12)
    assert got == {"level": "attention", "says": "idle; run 12's tool frame not yet given back to the controller"}
