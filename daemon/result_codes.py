"""The panel's result register (docs/panel.md): why a run ended as it did, and what each code
means in words (the status page, ``cellcal runs`` and the docs say the same)."""
from __future__ import annotations

import enum

from cellcal.drivers.interfaces import DeviceError, DeviceTimeout


class ResultCode(enum.IntEnum):
    """The panel's result register: why the last run ended as it did (docs/panel.md)."""

    OK = 0
    NOT_READY = 10
    NO_SUCH_ROUTINE = 11
    LIMITS = 12
    BUSY = 13
    TOOL_NOT_MOUNTED = 14
    CALIBRATE_FIRST = 15
    SENSOR_FAULT = 20
    ROBOT_FAULT = 21
    DEVICE_TIMEOUT = 22
    COMPUTATION_FAILED = 30
    GATE_FAILED = 31
    WRITE_BACK_FAILED = 32
    CHECK_ALARM = 33
    DRIFT_ALARM = 34
    ABORTED = 40
    INTERRUPTED = 41
    CONFIRM_TIMEOUT = 42
    SERVICE_FAULT = 50


RESULT_MEANINGS = {
    ResultCode.OK: "the run passed every gate and its tool frame was written back and read back",
    ResultCode.NOT_READY: "start refused: the robot is not ready (protective or emergency stop, not connected)",
    ResultCode.NO_SUCH_ROUTINE: "start refused: the routine selector names no routine this cell can run",
    ResultCode.LIMITS: "a move would leave the cell's limits: at the start, the routine's plan (nothing "
                       "moved); during the run, a move checked from where the arm is (refused before it was "
                       "sent; the arm stopped)",
    ResultCode.BUSY: "start refused: a routine is already running (the press is ignored)",
    ResultCode.TOOL_NOT_MOUNTED: "start refused: no tool is mounted (or one the cell lacks), or the tool selector "
                                 "names another tool than the mounted one or one the cell does not have; nothing "
                                 "moved",
    ResultCode.CALIBRATE_FIRST: "start refused: the check has nothing to judge against yet (no beam calibration "
                                "for the cell); the reason says what to run first (tcp-laser); nothing moved",
    ResultCode.SENSOR_FAULT: "the trigger or the tracker failed or went silent; motion stopped",
    ResultCode.ROBOT_FAULT: "the robot faulted (connection lost, protective or emergency stop); motion stopped",
    ResultCode.DEVICE_TIMEOUT: "the robot controller did not answer in time (stalled); motion stopped",
    ResultCode.COMPUTATION_FAILED: "the measurements could not be solved (the routine says why)",
    ResultCode.GATE_FAILED: "the result failed a quality gate and was not written back",
    ResultCode.WRITE_BACK_FAILED: "the controller did not keep the written tool frame; the old one was restored",
    ResultCode.CHECK_ALARM: "the tool check found the tool beyond its outer band, or could not tell: nothing "
                            "written; calibrate it deliberately (or replace a bent tool)",
    ResultCode.DRIFT_ALARM: "the tool check found the tool drifted beyond its drift alarm since the last full "
                            "calibration (the reason gives the numbers): nothing written; calibrate it",
    ResultCode.ABORTED: "aborted by the operator or by a stop of the service; nothing written back",
    ResultCode.INTERRUPTED: "the service died during the run; found at the next start, nothing written back",
    ResultCode.CONFIRM_TIMEOUT: "the routine waited for the operator's confirm (the plate moved to its next "
                                "placement) longer than its confirm_timeout_s; motion had stopped, nothing "
                                "written",
    ResultCode.SERVICE_FAULT: "the service could not keep its own records (state folder, datasets, store); "
                              "nothing written back",
}


def device_code(robot_name: str | None, exc: DeviceError) -> ResultCode:
    """The code of a device fault: the robot's (a timeout: it stalled) or a sensor's."""
    if exc.device == robot_name or "robot" in exc.device:
        return ResultCode.DEVICE_TIMEOUT if isinstance(exc, DeviceTimeout) else ResultCode.ROBOT_FAULT
    return ResultCode.SENSOR_FAULT  # the trigger or the tracker failed or went silent
