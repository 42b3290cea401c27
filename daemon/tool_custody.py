"""Custody of the tool frames on the controllers, between runs and around them.

* which tool a run is for (:meth:`ToolCustody.mount`): the mounted one, read from the cell
  file's source (fixed, the panel's register or the tool changer's inputs on the robot);
* a tool change: the controller's running tool frame made the mounted tool's own (the last
  frame written or restored for it, else its drawing) before anything moves;
* the frames owed: a run that wrote none gives each robot it moved the frame it had before
  (:class:`~cellcal.routines.framework.frames_owed.FramesOwed`, robot a's also in the store);
  when a fault leaves a robot unable to take it, the idle loop gives it back once the robot
  is ready again, and no run that moves that robot starts before;
* a robot whose connection was lost is reconnected off the main loop.
"""
from __future__ import annotations

import logging
import threading
import time

import numpy as np

from cellcal.daemon import cells
from cellcal.daemon.frame_writer import TOLERANCE
from cellcal.daemon.result_codes import ResultCode
from cellcal.drivers.interfaces import DeviceError, RobotState
from cellcal.routines.framework.frames_owed import ROBOT_A, FramesOwed

log = logging.getLogger("cellcal.daemon")

RECONNECT_AFTER_S = 2.0  # a robot unusable this long is reconnected (a busy moment is not a lost link)
RECONNECT_EVERY_S = 5.0  # and tried again this often while it stays lost


def _state_of(robot) -> RobotState:
    try:
        return robot.state()
    except DeviceError:
        return RobotState.DISCONNECTED


class ToolCustody:
    """The tool frames of `service`'s cell (:class:`~cellcal.daemon.service.Service`: its cell,
    drivers, store and events). `reconnect`: callable() -> a fresh set of the cell's drivers, or None."""

    def __init__(self, service, reconnect=None):
        self.service = service
        cell = service.cell
        self.reconnect = reconnect
        self.reconnect_at: float | None = None  # when the robot is to be reconnected (it is unusable)
        self.reconnecting: threading.Thread | None = None  # the reconnection under way, off the main loop
        self.owed = FramesOwed(settled=service.store.frame_settled if service.store is not None else None)
        # the tool the run under way (or the last) is for, and its view of the cell
        self.run_tool = 0 if cell.tool is None else int(cell.tool.id)
        self.run_cell = cell
        # the tool whose frame the controller's running tool frame holds (None: not known, the
        # mounted tool is read at each start: the first run sets its tool's frame)
        self.tcp_tool: int | None = self.run_tool if cell.mounted_source.kind == "file" else None

    # -- which tool -----------------------------------------------------------------------

    def mount(self, tool: int) -> str | None:
        """Decide the tool this run is for: the mounted one, read from the cell file's source;
        ``run_tool`` and ``run_cell`` are then that tool's. Returns why a start for tool `tool`
        (the selector; 0: whichever is mounted) may not run, or None."""
        cell = self.service.cell
        tools, source = cell.tools, cell.mounted_source
        try:
            mounted = cells.mounted_tool(cell, self.service.drivers)
        except cells.NoToolMounted as exc:
            self.run_tool = tool if tool in tools else 0
            return f"{exc}; nothing moved"
        except DeviceError as exc:
            self.run_tool = tool if tool in tools else 0
            return f"which tool is mounted cannot be read from {source.describe()}: {exc}; nothing moved"
        if mounted != self.run_tool and mounted in tools:
            log.info("tool %d (%s) is mounted (%s)", mounted, tools[mounted].name, source.describe())
        drawn = cell.tool
        if mounted == 0 or mounted not in tools or (drawn is not None and drawn.id == mounted):
            self.run_cell = cell
        elif self.run_cell.tool is None or self.run_cell.tool.id != mounted:
            self.run_cell = cell.with_tool(mounted)
        self.run_tool = mounted
        if tool == 0:
            return None
        if tool not in tools:
            have = ", ".join(f"{t.id} {t.name}" for t in tools.values()) or "none"
            return f"the tool selector names tool {tool}; this cell has no such tool (its tools: {have}); nothing moved"
        if tool != mounted:
            return (f"the tool selector names tool {tool} ({tools[tool].name}) but tool {mounted} "
                    f"({tools[mounted].name}) is mounted ({source.describe()}); nothing moved")
        return None

    def tool_changed(self) -> bool:
        """The controller's running frame is not (known to be) the mounted tool's."""
        return self.tcp_tool != self.run_tool

    def held_frame(self, tool_id: int) -> tuple[np.ndarray, str]:
        """The frame the controller holds for tool `tool_id` (m, rad) and where it comes from:
        the last frame written or restored for it in this store, else the tool as drawn."""
        written = self._last_written(tool_id)
        if written is not None:
            return written
        return np.asarray(self.service.cell.tools[tool_id].tcp_pose, dtype=float), "its drawing (never calibrated here)"

    def _last_written(self, tool_id: int) -> tuple[np.ndarray, str] | None:
        """The last frame written or restored for tool `tool_id` in this store, and its origin in words."""
        rows = [r for r in self.service.store.tool_frames() if int(r.get("tool_id") or 1) == tool_id]
        if not rows:
            return None
        row = rows[-1]
        done = "written" if row["action"] == "write" else "restored"
        return np.asarray(row["frame_after"], dtype=float), f"the last frame {done} for it (run {row['run_id']})"

    def not_the_written_frame(self, controller_frame) -> tuple[np.ndarray, str, str] | None:
        """At a start with no tool change: when the controller holds another frame than the last one
        written or restored for the mounted tool in this store (a controller restarted without it, a
        frame changed on the pendant), (that frame, where it is from, why it is set), else None. A
        tool never calibrated here has no such frame: whatever the controller holds stays (a check of
        a controller holding none compares with the tool's drawing)."""
        written = self._last_written(self.run_tool)
        if written is None:
            return None
        frame, origin = written
        held = np.asarray(controller_frame, dtype=float)
        if held.shape == frame.shape and np.abs(held - frame).max() <= TOLERANCE:
            return None
        what = ("holds no tool frame (all zero: a restarted controller without it?)" if not np.any(held) else
                f"holds {np.round(held, 6).tolist()}, {np.linalg.norm(held[:3] - frame[:3]) * 1e3:.3f} mm from it "
                "(a restarted controller, or a frame changed on the pendant?)")
        return frame, origin, f"the controller {what}"

    def tool_frame_for_mounted(self, run_id: int, frame: np.ndarray, origin: str, why: str | None = None):
        """A tool change, or a controller that holds another frame than the mounted tool's (`why`:
        :meth:`not_the_written_frame`): the controller's running tool frame is made the mounted tool's
        own (`frame`, from `origin`: :meth:`held_frame`) before anything moves, so the run measures
        against it. Returns None, or the refusal (code, why)."""
        tool_id = self.run_tool
        robot = self.service.drivers.robot
        try:
            robot.set_tcp(frame)
            back = np.asarray(robot.tool_frame(), dtype=float)
        except DeviceError as exc:
            return ResultCode.NOT_READY, f"tool {tool_id}'s frame could not be set on the controller: {exc}"
        if np.abs(back - frame).max() > TOLERANCE:  # doubles travel exactly
            return ResultCode.ROBOT_FAULT, (f"the controller reports {back.tolist()} after tool {tool_id}'s frame "
                                            f"{frame.tolist()} was set")
        self.tcp_tool = tool_id
        if why is None:
            message = f"tool {tool_id} ({self.run_cell.tool.name}) mounted: the controller's tool frame set to {origin}"
        else:
            message = f"{why}: tool {tool_id}'s frame set to {origin} before anything moves"
        log.info("run %d: %s", run_id, message)
        self.service.event("tool_frame_for_tool", f"run {run_id}: {message}")
        return None

    # -- the frames owed ------------------------------------------------------------------

    def robots(self) -> dict:
        """The cell's robots by name, robot a (``drivers.robot``) included."""
        drivers = self.service.drivers
        return {**drivers.robots, ROBOT_A: drivers.robot}

    def other_robots(self) -> dict:
        """The cell's robots besides robot a, by name."""
        drivers = self.service.drivers
        return {name: robot for name, robot in drivers.robots.items()
                if name != ROBOT_A and robot is not drivers.robot}

    def owe(self, run_id: int, frame_before: np.ndarray) -> None:
        """Before run `run_id` moves: each robot is owed its frame from before (robot a's as the
        run read it, also in the store) until the run gives it back or writes a new one."""
        self.owed.owe(run_id, self.robots(), known={ROBOT_A: frame_before})
        self.service.store.owe_frame(run_id, frame_before)

    def written(self) -> None:
        """The run's frame is robot a's now: it is owed its old one no more."""
        self.owed.settle(ROBOT_A)

    def owed_by(self, run_id: int) -> bool:
        return self.owed.run_of(ROBOT_A) == run_id

    def waiting(self, robots) -> str | None:
        """Why a routine that moves `robots` must not start yet (a frame owed not yet back), or None."""
        return self.owed.waiting({ROBOT_A, *robots})

    def resume_owed_frame(self) -> int | None:
        """At start-up: a tool frame a run owes the controller (a fault or a stop of the
        service left the tool as drawn on it) is given back by the idle loop once the robot
        is ready; a frame from before a newer write is stale and never comes back. Returns
        the run it is owed for."""
        owed = self.service.store.owed_frame()
        if owed is None:
            return None
        run_id, frame = owed
        self.owed.owe(run_id, {ROBOT_A: None}, known={ROBOT_A: frame})
        log.info("run %d left the controller on another tool frame than before it: it is given back once the "
                 "robot is ready", run_id)
        return run_id

    # -- between runs ---------------------------------------------------------------------

    def robot_state(self) -> RobotState:
        state = _state_of(self.service.drivers.robot)
        self.service.seen["robot"] = state.value
        return state

    def recover(self) -> None:
        """Between runs: reconnect a robot whose connection was lost (once it has been unusable
        for RECONNECT_AFTER_S, then every RECONNECT_EVERY_S, in a thread of its own so the
        panel is served meanwhile), and give each robot back the tool frame a run that wrote
        none left changed."""
        if self.reconnecting is not None:
            if self.reconnecting.is_alive():
                return
            self.reconnecting = None
        state, now = self.robot_state(), time.monotonic()
        lost = state is RobotState.DISCONNECTED or any(
            _state_of(robot) is RobotState.DISCONNECTED for robot in self.other_robots().values())
        if not lost or self.reconnect is None:
            self.reconnect_at = None
        elif self.reconnect_at is None:
            self.reconnect_at = now + RECONNECT_AFTER_S
        elif now >= self.reconnect_at:
            self.reconnect_at = now + RECONNECT_EVERY_S
            self.reconnecting = threading.Thread(target=self._reconnect, name="cellcal-reconnect", daemon=True)
            self.reconnecting.start()
            return
        if self.owed:
            robots = self.other_robots()
            if state is RobotState.READY:  # robot a last, as its readiness was just read
                robots[ROBOT_A] = self.service.drivers.robot
            self.owed.give_back(robots, self.service.event)

    def recover_quietly(self) -> None:
        try:
            self.recover()
        except Exception as exc:
            log.error("giving the tool frame back failed: %s", exc)

    def _reconnect(self) -> None:
        """Off the main loop: the lost robots' connections closed (a controller may let only one
        client hold its inputs), a fresh set of the cell's devices opened, and swapped in
        under the panel's lock, so no panel call runs on a device being replaced; the main
        loop starts no run meanwhile (NOT_READY)."""
        service = self.service
        old = service.drivers
        for robot in dict.fromkeys([*old.robots.values(), old.robot]):
            try:
                robot.close()
            except Exception as exc:
                log.info("closing the lost connection: %s", exc)
        try:
            fresh = self.reconnect()
        except Exception as exc:  # anything a half-reachable cell raises: the service keeps running
            log.warning("the robot's connection is still lost: %s", exc)
            return
        with service.panel.lock:
            service.drivers = fresh
        for device in (old.trigger, old.tracker, old.panel):
            if device is not None:
                try:
                    device.close()
                except Exception as exc:
                    log.info("closing the replaced connection: %s", exc)
        log.info("reconnected the cell's devices")
        service.event("reconnected", None)
        self.reconnect_at = None
