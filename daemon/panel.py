"""The panel protocol (docs/panel.md): the start, abort and confirm buttons as the service's
main loop reads them, the lamps, the result code and the outcome registers it writes, and the
operator at the panel as a routine asks them (:class:`PanelOperator`).

Every call survives a dropped connection (logged once per drop); a start request pending
when the panel comes back is discarded, never taken: a press nobody can vouch for never
starts a run. The abort button is read first and wins over a start or a confirm.
"""
from __future__ import annotations

import logging
import threading
import time

from cellcal.daemon import outcome
from cellcal.daemon.result_codes import ResultCode
from cellcal.drivers.interfaces import DeviceError, Operator, OperatorTimeout
from cellcal.routines.framework import registry
from cellcal.routines.framework.base import RoutineAborted

log = logging.getLogger("cellcal.daemon")


def panel_routines() -> dict[int, str]:
    """The routine selector register's values (docs/panel.md) -> routine names, as the routine
    table lists them (:mod:`cellcal.routines.framework.table`, read through the registry)."""
    return registry.panel_selectors()


class PanelProtocol:
    """The panel of `service`'s cell (:class:`~cellcal.daemon.service.Service`), read and
    written one caller at a time (``lock``: also keeps a reconnection from swapping the
    drivers under a call)."""

    def __init__(self, service):
        self.service = service
        self.lock = threading.Lock()
        self.ok = True
        self.unconfirmed = False  # the panel just came back: a pending start is not taken
        self.waiting = 0  # the step a routine waits for the operator to confirm (PanelOperator); 0: none waits
        self.confirmed = threading.Event()  # the confirm button, pressed while a routine waits

    def call(self, what: str, *args, **kwargs):
        """A panel call that survives a dropped connection (logged once per drop)."""
        with self.lock:
            panel = self.service.drivers.panel
            if panel is None:
                return None
            try:
                value = getattr(panel, what)(*args, **kwargs)
            except DeviceError as exc:
                if self.ok:
                    self.ok = False
                    log.warning("panel lost: %s", exc)
                    self.service.event("panel_lost", str(exc))
                return None
        if not self.ok:
            self.ok, self.unconfirmed = True, True
            log.info("panel back")
            self.service.event("panel_back", None)
        return value

    # -- the buttons ----------------------------------------------------------------------

    def poll(self) -> None:
        """One look at the panel: abort while running; a start request otherwise. The abort
        button is read first: a start pressed together with it (or while it is held) is
        refused, and an abort always stops a run it finds."""
        service = self.service
        if service.busy():
            if self.call("abort_requested"):
                service.request_abort("abort button")
            self.take_confirm()
            if self.call("start_requested"):
                log.info("start pressed while run %s is going on: refused (result code %d BUSY)",
                         service.run_id, ResultCode.BUSY)
                service.event("start_refused_busy", f"run {service.run_id}")
                self.call("set_result", int(ResultCode.BUSY), increment_counter=False)
            return
        service.custody.recover()
        aborted = self.call("abort_requested")  # an abort with nothing running is cleared, not remembered
        self.take_confirm()
        pressed = self.call("start_requested")
        if pressed is None:
            return
        unconfirmed, self.unconfirmed = self.unconfirmed, False
        if pressed and aborted:
            self.abort_wins("pressed together with abort (abort wins)")
        elif pressed and unconfirmed:
            self.discarded("pending when the panel came back")
        elif pressed:
            selector = self.call("routine_selector")
            if selector is None:  # the request cannot be confirmed: never start from it
                log.warning("start request seen but the routine selector could not be read: not started")
                return
            tool = self.call("tool_selector")
            if tool is None:
                log.warning("start request seen but the tool selector could not be read: not started")
                return
            if self.call("abort_requested"):  # abort pressed meanwhile (or with it, read apart): it wins
                self.abort_wins("followed by abort before it was taken (abort wins)")
                return
            service.start(service.routines.get(int(selector), f"selector {selector}"), tool=int(tool))

    def discard_requests(self, why: str) -> None:
        """Clear the panel's requests without acting on them (those pending when the service
        starts: a press nobody can vouch for never starts a run)."""
        if self.call("start_requested"):
            self.discarded(why)
        self.call("abort_requested")
        self.call("confirm_requested")
        self.call("set_waiting", 0)

    def take_confirm(self) -> None:
        """The confirm button: it answers a routine waiting for the operator (the abort button,
        read before it, wins); pressed while none waits it is cleared and ignored."""
        if not self.call("confirm_requested"):
            return
        service = self.service
        if self.waiting:
            log.info("run %s: the operator confirmed step %d", service.run_id, self.waiting)
            self.confirmed.set()
        else:
            log.info("confirm pressed while no routine waits for it: cleared, ignored")
            service.event("confirm_ignored", None if service.run_id is None or not service.busy()
                          else f"run {service.run_id}")

    def abort_wins(self, why: str) -> None:
        """A start the abort button overrules: nothing starts, and the press is answered
        (result code 40, counted, so a PLC waiting on the counter sees it)."""
        self.discarded(why)
        self.call("set_lamps", done=False, fault=False)
        self.call("set_result", int(ResultCode.ABORTED))

    def discarded(self, why: str) -> None:
        log.warning("a start request %s: cleared, not started (press start again)", why)
        self.service.event("start_discarded", why)

    # -- what the panel shows -------------------------------------------------------------

    def show_state(self, state: str) -> None:
        """The busy lamp for a run's state (a new run: the last one's lamps are history)."""
        if state == "checking":
            self.call("set_lamps", busy=True, done=False, fault=False)
        elif state not in ("idle", "done", "fault", "refused", "aborted"):
            self.call("set_lamps", busy=True)

    def show_end(self, code: ResultCode, *, done: bool, fault: bool, verdict, tool_id: int, change) -> None:
        """A run's end: the lamps (done: a frame went to the controller), the outcome registers,
        then the result code and the run counter."""
        self.call("set_lamps", busy=False, done=done, fault=fault)
        self.call("set_outcome", outcome.registers(verdict, tool_id, change))
        self.call("set_result", int(code))

    def announce_interrupted(self, run_ids: list[int]) -> None:
        """Runs a previous process died in (found at start-up): the panel says so, result
        code INTERRUPTED and the fault lamp, until the next run."""
        if run_ids:
            self.call("set_lamps", busy=False, done=False, fault=True)
            self.call("set_result", int(ResultCode.INTERRUPTED), increment_counter=False)


class PanelOperator(Operator):
    """The operator at the panel, as a routine asks them (:class:`~cellcal.drivers.interfaces.Operator`):
    the waiting lamp lit and the step (the placement) in its register, the message in the log and the
    status page's progress, until the confirm button (read by the service's panel loop), the abort
    button (the run ends aborted: abort wins) or the timeout (CONFIRM_TIMEOUT)."""

    name = "operator at the panel"
    LOOK_S = 0.05  # how often the wait looks at the abort event between confirm presses

    def __init__(self, service, run_id: int):
        self.service, self.run_id = service, run_id

    def confirm(self, message: str, *, step: int, timeout_s: float) -> None:
        service, panel = self.service, self.service.panel
        panel.confirmed.clear()
        panel.waiting = int(step)  # before the lamp: a press the lamp asked for is never taken as early
        panel.call("set_waiting", int(step))
        service.event("waiting_for_operator", f"run {self.run_id}: {message}")
        deadline = time.monotonic() + timeout_s
        service.seen["waiting"] = {"message": message, "step": int(step), "until": time.time() + timeout_s}
        try:
            while True:
                if service.abort.is_set():
                    raise RoutineAborted(f"aborted while waiting for the operator ({message})")
                if panel.confirmed.wait(self.LOOK_S):
                    if service.abort.is_set():  # pressed together with abort: abort wins
                        raise RoutineAborted(f"aborted while waiting for the operator ({message})")
                    return
                if time.monotonic() >= deadline:
                    raise OperatorTimeout(self.name, f"no confirm within {timeout_s:g} s (confirm_timeout_s) "
                                                     f"after asking: {message}")
        finally:
            service.seen["waiting"] = None
            panel.waiting = 0
            panel.confirmed.clear()
            panel.call("set_waiting", 0)
