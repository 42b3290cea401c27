"""The daemon's service in process, driven from its operator panel as the service tests press
it (the panel of the in-process cell in memory, or the Modbus one of a networked cell)."""
from __future__ import annotations

from cellcal.routines.framework.registry import panel_selectors

SELECT = {name: number for number, name in panel_selectors().items()}  # routine name -> the panel's selector
RUN_WAIT_S = 120.0


def press(service, panel, routine: str | int, *, abort: bool = False, timeout_s: float = RUN_WAIT_S):
    """The operator selects `routine` (a name; a number is put on the selector as it is) and
    presses start (abort with it when `abort`); the service takes the press. The run's outcome."""
    panel.select_routine(SELECT.get(routine, routine))
    panel.press_start()
    if abort:
        panel.press_abort()
    service.poll_panel()
    return service.wait(timeout_s)
