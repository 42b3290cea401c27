"""Trigger event to position: how far the position interpolated at a trigger's time is
from where the beam really was crossed, per transport and sweep speed.

Used by :mod:`bench.drivers_bench` (part 2); run it through that module.

* **Robot digital input (RTDE).** Entirely real: the fake UR controller (another
  process, loopback) runs ``moveL`` sweeps through a ``LightBeam`` on input 2 under
  :class:`UrRtdeRobot`; :class:`UrDigitalInputTrigger` shares the robot's lossless state
  stream. The event time is the first 2 ms controller cycle showing the new level, the
  position is interpolated in the robot's own timestamped 500 Hz pose stream, and the
  truth is the beam edge's position (beam axis ± radius along the sweep).
* **Modbus TCP, serial, CAN (device-timestamped).** The real adapters read from the real
  fakes (pymodbus server on loopback with the default 5 ms poll, a pseudo-terminal
  pair, python-can's virtual bus). The motion is simulated: a point moving at constant
  speed, whose true crossing times are known exactly, on the host's monotonic clock,
  which here plays the robot's clock. The barrier scans its input every
  ``DEVICE_SCAN_S`` at a random phase, stamps the first scan that sees the new level on
  its own µs counter (random offset; integer µs), and sends the record over the
  transport when that scan happens, in real time. The routine maps device time to robot
  time with the offset, taken as known (as after a clock sync; sync error and drift are
  not modelled), and interpolates a 500 Hz pose stream at a random phase. For
  contrast, the position at the event's *arrival* time is reported too: what a routine
  would get by timing edges on arrival instead of by the device.
"""
from __future__ import annotations

import sys
import threading
import time
import uuid

import numpy as np

from cellcal.drivers.interfaces import Edge

SPEEDS_MM_S = (20.0, 40.0, 100.0)
BEAM_RADIUS_M = 0.001  # half the beam width plus the tip radius: edges 2 mm apart
DEVICE_SCAN_S = 100e-6  # the barrier's input scan (a timestamping IO input, 10 kHz)
POSE_PERIOD_S = 0.002  # the pose stream the routine interpolates: 500 Hz
SWEEP_TRAVEL_M = 0.03  # RTDE sweeps: 30 mm with the beam in the middle
SWEEP_ACCEL_M_S2 = 1.2  # 100 mm/s reached within 4.2 mm, well before the beam
SWEEP_JITTER_M = 0.001  # each sweep ends up to 1 mm further out, so crossings fall at any cycle phase
LEAD_S = 0.03  # device sweeps: the first edge this long after the sweep is scheduled


def log(msg: str) -> None:
    print(f"[drivers-bench] {msg}", file=sys.stderr, flush=True)


def error_stats(errors_m) -> dict:
    """Signed errors (positive: the position is late along the sweep) -> summary in mm."""
    e = np.asarray(errors_m, dtype=float) * 1000.0
    if e.size == 0:
        return {"n": 0, "mean_mm": float("nan"), "mean_abs_mm": float("nan"), "max_abs_mm": float("nan")}
    return {"n": int(e.size), "mean_mm": float(e.mean()), "mean_abs_mm": float(np.abs(e).mean()),
            "max_abs_mm": float(np.abs(e).max())}


# -- robot digital input through RTDE ------------------------------------------------

def rtde_trigger_sweeps(host: str, sweeps: int, seed: int = 0, speeds_mm_s=SPEEDS_MM_S) -> list[dict]:
    from cellcal.drivers.ur.robot import UrRtdeRobot
    from cellcal.drivers.ur.trigger import UrDigitalInputTrigger
    from cellcal.sims.fake_ur.process import FakeUrProcess

    rng = np.random.default_rng(seed)
    rows = []
    with FakeUrProcess(host) as fake:
        robot = UrRtdeRobot(host)
        trigger = None
        try:
            start = robot.actual_tcp_pose()
            beam_x = start[0] + SWEEP_TRAVEL_M / 2
            fake.request(cmd="add_model", model={"kind": "beam", "point_m": [beam_x, start[1], start[2]],
                                                 "direction": [0, 0, 1], "radius_m": BEAM_RADIUS_M,
                                                 "channel": 2})
            trigger = UrDigitalInputTrigger(stream=robot.state_stream, channels=(2,))
            for speed in speeds_mm_s:
                errors, missing = [], 0
                for i in range(sweeps):
                    forward = i % 2 == 0
                    trigger.events()  # nothing left over from the last sweep
                    # the controller's motion is locked to its cycle: a sweep of the same length
                    # would cross the beam at the same phase every time, so the ends vary
                    target = start.copy()
                    target[0] += SWEEP_TRAVEL_M + rng.uniform(0, SWEEP_JITTER_M) if forward \
                        else -rng.uniform(0, SWEEP_JITTER_M)
                    robot.move_l(target, speed / 1000.0, SWEEP_ACCEL_M_S2)
                    events = []
                    deadline = time.monotonic() + 2.0
                    while len(events) < 2 and time.monotonic() < deadline:
                        events += trigger.events(timeout_s=0.2)
                    samples = robot.samples()
                    t = np.array([s.t_s for s in samples])
                    x = np.array([s.tcp_pose[0] for s in samples])
                    sign = 1.0 if forward else -1.0
                    edges = {Edge.BLOCKED: beam_x - sign * BEAM_RADIUS_M, Edge.CLEARED: beam_x + sign * BEAM_RADIUS_M}
                    missing += max(0, 2 - len(events))
                    for event in events[:2]:
                        errors.append(sign * (float(np.interp(event.t_s, t, x)) - edges[event.edge]))
                row = {"transport": "robot DI (RTDE)", "speed_mm_s": speed, "edges_expected": 2 * sweeps,
                       "edges_missing": missing, "device_time": error_stats(errors),
                       "arrival_time": None, "latency_ms": None}
                rows.append(row)
                d = row["device_time"]
                log(f"RTDE digital input {speed:5.0f} mm/s: {d['n']} edges, "
                    f"mean |e| {d['mean_abs_mm']:.4f} mm, max {d['max_abs_mm']:.4f} mm")
        finally:
            if trigger is not None:
                trigger.close()
            robot.close()
    return rows


# -- device-timestamped transports ---------------------------------------------------

class _ModbusLink:
    label = "Modbus TCP"

    def __init__(self):
        from cellcal.drivers.modbus.trigger import ModbusTrigger
        from cellcal.sims.net.modbus_server import ModbusCellServer

        self.server = ModbusCellServer(ring_size=16).start()
        self.trigger = ModbusTrigger(port=self.server.port)  # default poll, 5 ms

    def send(self, channel, edge, t_us):
        self.server.record_edge(channel, edge, t_us)

    def close(self):
        self.trigger.close()
        self.server.stop()


class _SerialLink:
    label = "serial"

    def __init__(self):
        from cellcal.drivers.triggers.serial_line import SerialTrigger
        from cellcal.sims.net.serial_barrier import SerialBarrier

        self.barrier = SerialBarrier()
        self.trigger = SerialTrigger(self.barrier.tty_path)

    def send(self, channel, edge, t_us):
        self.barrier.send_edge(channel, edge, t_us)

    def close(self):
        self.trigger.close()
        self.barrier.close()


class _CanLink:
    label = "CAN"

    def __init__(self):
        from cellcal.drivers.triggers.can_bus import CanTrigger
        from cellcal.sims.net.can_barrier import CanBarrier

        channel = f"cellcal-bench-{uuid.uuid4().hex}"
        self.trigger = CanTrigger(channel, interface="virtual")
        self.barrier = CanBarrier(channel)

    def send(self, channel, edge, t_us):
        self.barrier.send_edge(channel, edge, t_us)

    def close(self):
        self.trigger.close()
        self.barrier.close()


DEVICE_LINKS = (_ModbusLink, _SerialLink, _CanLink)


def _device_sweep(link, rng, speed_m_s: float, offset_us: int) -> list[dict]:
    """One simulated sweep through the beam; returns one record per received edge."""
    t_blocked = time.monotonic() + LEAD_S
    truths = ((Edge.BLOCKED, t_blocked, -BEAM_RADIUS_M), (Edge.CLEARED, t_blocked + 2 * BEAM_RADIUS_M / speed_m_s,
                                                           BEAM_RADIUS_M))
    scan_phase = rng.uniform(0.0, DEVICE_SCAN_S)
    plan = []
    for edge, t_true, x_edge in truths:
        t_scan = scan_phase + np.ceil((t_true - scan_phase) / DEVICE_SCAN_S) * DEVICE_SCAN_S
        t_us = int(np.floor(t_scan * 1e6)) + offset_us  # the device's counter, whole µs
        plan.append((edge, t_true, x_edge, t_scan, t_us))
    sent_at: dict = {}

    def device():
        for edge, _, _, t_scan, t_us in plan:
            delay = t_scan - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            sent_at[edge] = time.monotonic()
            link.send(1, edge, t_us % 2**32)

    sender = threading.Thread(target=device, name="bench-barrier", daemon=True)
    sender.start()
    received = []
    deadline = t_blocked + 2 * BEAM_RADIUS_M / speed_m_s + 1.0
    while len(received) < 2 and time.monotonic() < deadline:
        events = link.trigger.events(timeout_s=0.05)
        now = time.monotonic()
        received += [(event, now) for event in events]
    sender.join(2.0)

    # the robot's pose stream: 500 Hz at a random phase around the sweep, x = 0 at the beam
    x_of = (lambda t: (t - t_blocked) * speed_m_s - BEAM_RADIUS_M)
    t_grid = t_blocked - 0.2 + rng.uniform(0.0, POSE_PERIOD_S) + POSE_PERIOD_S * np.arange(
        int((0.6 + 2 * BEAM_RADIUS_M / speed_m_s) / POSE_PERIOD_S))
    x_grid = x_of(t_grid)
    out = []
    by_edge = {p[0]: p for p in plan}
    unwrap_us = None
    for event, arrival in received:
        edge, t_true, x_edge, _, t_us = by_edge[event.edge]
        # device seconds -> robot clock: the adapter's t_s is the unwrapped µs counter
        if unwrap_us is None:
            unwrap_us = t_us - round(event.t_s * 1e6)  # whole wraps the adapter has not counted
        t_robot = (event.t_s * 1e6 + unwrap_us - offset_us) / 1e6
        out.append({"edge": edge, "error_m": float(np.interp(t_robot, t_grid, x_grid)) - x_edge,
                    "arrival_error_m": float(np.interp(arrival, t_grid, x_grid)) - x_edge,
                    "latency_s": arrival - sent_at.get(edge, np.nan), "t_true": t_true})
    return out


def device_trigger_sweeps(sweeps: int, seed: int = 0, speeds_mm_s=SPEEDS_MM_S) -> list[dict]:
    rng = np.random.default_rng(seed)
    rows = []
    for link_class in DEVICE_LINKS:
        link = link_class()
        try:
            offset_us = int(rng.integers(0, 2**32))  # the barrier's counter, unrelated to ours
            for speed in speeds_mm_s:
                records = []
                for _ in range(sweeps):
                    records += _device_sweep(link, rng, speed / 1000.0, offset_us)
                    time.sleep(rng.uniform(0.0, 0.01))  # sweeps start at unrelated times
                latencies_ms = np.array([r["latency_s"] for r in records]) * 1000.0
                row = {"transport": link.label, "speed_mm_s": speed, "edges_expected": 2 * sweeps,
                       "edges_missing": 2 * sweeps - len(records),
                       "device_time": error_stats([r["error_m"] for r in records]),
                       "arrival_time": error_stats([r["arrival_error_m"] for r in records]),
                       "latency_ms": {"median": float(np.nanmedian(latencies_ms)),
                                      "max": float(np.nanmax(latencies_ms))} if records else None}
                rows.append(row)
                log(f"{link.label:10s} {speed:5.0f} mm/s: {len(records)} edges, device time mean |e| "
                    f"{row['device_time']['mean_abs_mm']:.5f} mm, arrival time mean |e| "
                    f"{row['arrival_time']['mean_abs_mm']:.3f} mm")
        finally:
            link.close()
    return rows


def print_trigger_table(rows: list[dict]) -> None:
    print("\nTrigger event -> interpolated position, error vs the true crossing (mm; + = late along the sweep)")
    print(f"{'transport':16s} {'mm/s':>5s} {'edges':>7s} {'mean':>8s} {'mean|e|':>8s} {'max|e|':>8s}"
          f" | {'arrival: mean|e|':>16s} {'max|e|':>7s} {'ratio':>7s} | {'latency med/max ms':>18s}")
    for r in rows:
        d, a, lat = r["device_time"], r["arrival_time"], r["latency_ms"]
        edges = f"{d['n']}/{r['edges_expected']}"
        line = (f"{r['transport']:16s} {r['speed_mm_s']:5.0f} {edges:>7s} {d['mean_mm']:8.4f} "
                f"{d['mean_abs_mm']:8.4f} {d['max_abs_mm']:8.4f}")
        if a is None:
            line += f" | {'(controller clock)':>16s} {'':>7s} {'':>7s} | {'':>18s}"
        else:
            ratio = a["mean_abs_mm"] / d["mean_abs_mm"] if d["mean_abs_mm"] > 0 else float("inf")
            line += (f" | {a['mean_abs_mm']:16.4f} {a['max_abs_mm']:7.3f} {ratio:6.0f}x"
                     f" | {lat['median']:8.2f} / {lat['max']:7.2f}")
        print(line)
