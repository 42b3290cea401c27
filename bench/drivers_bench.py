"""Bench: the device drivers against the fakes, in real time over loopback, a pty and a virtual bus.

    python -m bench.drivers_bench            # full: 2 x 60 s RTDE, 20/30 sweeps, 200 presses
    python -m bench.drivers_bench --quick    # smoke run, under a minute

1. RTDE receive at 500 Hz against the fake UR controller (its own process): every
   2 ms package counted by the controller's ``timestamp``, through our lossless reader
   (``drivers/ur/state.py``) and, in the same window, through ur_rtde's
   ``RTDEReceiveInterface`` polled every ``--poll-ms`` (in a child process, so that the
   two readers do not share a GIL); first idle, then with ``--busy`` CPU-bound
   processes running. Received/expected and lost, for each.
2. Trigger event to position per transport and speed (see :mod:`bench.trigger_bench`
   for how each transport is driven and what is simulated).
3. Operator panel: a start press in the fake Modbus server to ``ModbusPanel`` seeing
   it, polling every ``--panel-poll-ms``; the latency distribution.

Progress goes to stderr, tables to stdout, every number to bench/results/drivers.json.
One BLAS thread unless OPENBLAS_NUM_THREADS etc. say otherwise.
"""
from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from importlib import metadata  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

if __package__ in (None, ""):  # run as a script: make `bench` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.trigger_bench import (DEVICE_SCAN_S, SPEEDS_MM_S, device_trigger_sweeps, log,  # noqa: E402
                                 print_trigger_table, rtde_trigger_sweeps)

REPO = Path(__file__).resolve().parents[1]
CYCLE_HZ = 500.0
RTDE_VARIABLES = ("timestamp", "actual_q", "actual_TCP_pose", "actual_digital_input_bits")


def _hosts():
    base = f"127.9.{os.getpid() % 250 + 1}"
    return (f"{base}.{n}" for n in range(1, 255))


# -- part 1: RTDE receive ------------------------------------------------------------

def count_cycles(timestamps) -> dict:
    """Distinct controller cycles seen, against every cycle between the first and the last."""
    cycles = np.unique(np.round(np.asarray(timestamps, dtype=float) * CYCLE_HZ).astype(np.int64))
    if cycles.size == 0:
        return {"received": 0, "expected": 0, "lost": 0, "lost_pct": float("nan"), "longest_gap_cycles": 0}
    expected = int(cycles[-1] - cycles[0] + 1)
    gaps = np.diff(cycles) - 1
    return {"received": int(cycles.size), "expected": expected, "lost": expected - int(cycles.size),
            "lost_pct": 100.0 * (expected - cycles.size) / expected,
            "longest_gap_cycles": int(gaps.max()) if gaps.size else 0,
            "first_s": float(cycles[0] / CYCLE_HZ), "last_s": float(cycles[-1] / CYCLE_HZ)}


def rtde_poll_child(host: str, seconds: float, poll_ms: float) -> int:
    """Child process: poll ur_rtde's receive interface, print the timestamps it saw as JSON."""
    import rtde_receive

    receive = rtde_receive.RTDEReceiveInterface(host, -1.0, list(RTDE_VARIABLES))
    print("READY", flush=True)
    seen, period = [], poll_ms / 1000.0
    try:
        end = time.monotonic() + seconds
        next_t = time.monotonic()
        while time.monotonic() < end:
            seen.append(receive.getTimestamp())
            next_t += period
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
    finally:
        receive.disconnect()
    print(json.dumps({"timestamps": sorted(set(seen)), "polls": len(seen)}), flush=True)
    return 0


def rtde_receive_run(host: str, seconds: float, busy: int, poll_ms: float) -> dict:
    from cellcal.drivers.ur.state import UrStateStream
    from cellcal.sims.fake_ur.process import FakeUrProcess

    hogs = []
    with FakeUrProcess(host):
        child = subprocess.Popen([sys.executable, "-m", "bench.drivers_bench", "--rtde-poll-child", host,
                                  repr(seconds), repr(poll_ms)], cwd=REPO, stdout=subprocess.PIPE,
                                 stdin=subprocess.DEVNULL, text=True)
        stream = None
        try:
            if child.stdout.readline().strip() != "READY":
                raise RuntimeError("the ur_rtde polling process did not start")
            stream = UrStateStream(host, device="bench state stream", variables=RTDE_VARIABLES,
                                   buffer_s=seconds + 30.0)
            for _ in range(busy):  # CPU-bound neighbours, as on a busy cell PC
                hogs.append(subprocess.Popen([sys.executable, "-c", "while True: pass"]))
            load_start = os.getloadavg()
            time.sleep(seconds)
            ours = [s.t_s for s in stream.samples()]
            out, _ = child.communicate(timeout=seconds + 30.0)
            theirs = json.loads(out.strip().splitlines()[-1])
        finally:
            for hog in hogs:
                hog.terminate()
            for hog in hogs:
                hog.wait(5)
            if stream is not None:
                stream.close()
            if child.poll() is None:
                child.terminate()
                child.wait(5)
    result = {"busy_processes": busy, "seconds": seconds, "poll_ms": poll_ms,
              "lossless_reader": count_cycles(ours),
              "ur_rtde_polling": {**count_cycles(theirs["timestamps"]), "polls": theirs["polls"]},
              "load_average_start": load_start}
    for key, label in (("lossless_reader", "lossless reader"), ("ur_rtde_polling", "ur_rtde polling")):
        r = result[key]
        log(f"RTDE {busy} busy: {label:16s} {r['received']}/{r['expected']} lost {r['lost']}")
    return result


def print_rtde_table(runs: list[dict]) -> None:
    print("\nRTDE receive at 500 Hz, packages counted by controller timestamp")
    print(f"{'busy procs':>10s} {'reader':26s} {'received':>9s} {'expected':>9s} {'lost':>7s} {'lost %':>7s}"
          f" {'longest gap':>11s}")
    for run in runs:
        for key, label in (("lossless_reader", "ur_rtde_state (ours)"),
                           ("ur_rtde_polling", f"RTDEReceiveInterface {run['poll_ms']:g}ms")):
            r = run[key]
            print(f"{run['busy_processes']:10d} {label:26s} {r['received']:9d} {r['expected']:9d} {r['lost']:7d}"
                  f" {r['lost_pct']:7.2f} {r['longest_gap_cycles']:8d} cyc")


# -- part 3: panel --------------------------------------------------------------------

def panel_latency(presses: int, poll_s: float, seed: int = 0) -> dict:
    from cellcal.drivers.modbus.panel import ModbusPanel
    from cellcal.sims.net.modbus_server import ModbusCellServer

    rng = np.random.default_rng(seed)
    seen = threading.Event()
    seen_at: list[float] = []
    stop = threading.Event()
    errors: list[BaseException] = []
    with ModbusCellServer() as server:
        panel = ModbusPanel(port=server.port, timeout_s=1.0)

        def daemon_loop():  # the daemon's idle loop: poll the start request every poll_s
            next_t = time.monotonic()
            try:
                while not stop.is_set():
                    if panel.start_requested():
                        seen_at.append(time.monotonic())
                        seen.set()
                    next_t += poll_s
                    delay = next_t - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                    else:
                        next_t = time.monotonic()
            except BaseException as exc:
                errors.append(exc)

        poller = threading.Thread(target=daemon_loop, name="bench-panel-poll", daemon=True)
        poller.start()
        latencies, missed = [], 0
        try:
            for _ in range(presses):
                time.sleep(rng.uniform(0.0, 2 * poll_s))  # presses fall at any phase of the poll
                seen.clear()
                n_before = len(seen_at)
                t_press = time.monotonic()
                server.press_start()
                if not seen.wait(1.0) or errors:
                    missed += 1
                    continue
                latencies.append(seen_at[n_before] - t_press)
        finally:
            stop.set()
            poller.join(2.0)
            panel.close()
    if errors:
        raise errors[0]
    ms = np.array(latencies) * 1000.0
    result = {"presses": presses, "poll_ms": poll_s * 1000.0, "seen": int(ms.size), "missed": missed,
              "median_ms": float(np.median(ms)), "p95_ms": float(np.percentile(ms, 95)),
              "max_ms": float(ms.max()), "min_ms": float(ms.min()), "mean_ms": float(ms.mean())}
    log(f"panel: {result['seen']}/{presses} presses seen, median {result['median_ms']:.1f} ms")
    return result


def print_panel_table(r: dict) -> None:
    print(f"\nPanel start press -> ModbusPanel sees it (polling every {r['poll_ms']:g} ms)")
    print(f"{'presses':>8s} {'seen':>5s} {'min':>7s} {'median':>7s} {'p95':>7s} {'max':>7s}  ms"
          f"   median/poll period")
    print(f"{r['presses']:8d} {r['seen']:5d} {r['min_ms']:7.1f} {r['median_ms']:7.1f} {r['p95_ms']:7.1f}"
          f" {r['max_ms']:7.1f}      {r['median_ms'] / r['poll_ms']:.2f}")


# -- main ---------------------------------------------------------------------------

def _versions() -> dict:
    out = {"python": platform.python_version(), "numpy": np.__version__, "cpu_count": os.cpu_count()}
    for dist in ("ur_rtde", "pymodbus", "pyserial", "python-can"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = None
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: 5 s RTDE, few sweeps and presses")
    parser.add_argument("--rtde-seconds", type=float, help="RTDE window per load level (default 60, quick 5)")
    parser.add_argument("--busy", default="0,2", help="CPU-bound processes per RTDE run, comma-separated")
    parser.add_argument("--poll-ms", type=float, default=1.0, help="ur_rtde baseline polling period")
    parser.add_argument("--sweeps", type=int, help="RTDE trigger sweeps per speed (default 20, quick 4)")
    parser.add_argument("--device-sweeps", type=int, help="device trigger sweeps per speed (default 30, quick 5)")
    parser.add_argument("--presses", type=int, help="panel presses (default 200, quick 30)")
    parser.add_argument("--panel-poll-ms", type=float, default=20.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skip", default="", help="parts to leave out: rtde,trigger,panel")
    parser.add_argument("--rtde-poll-child", nargs=3, metavar=("HOST", "SECONDS", "POLL_MS"),
                        help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.rtde_poll_child:
        host, seconds, poll_ms = args.rtde_poll_child
        return rtde_poll_child(host, float(seconds), float(poll_ms))

    quick = args.quick
    seconds = args.rtde_seconds or (5.0 if quick else 60.0)
    sweeps = args.sweeps or (4 if quick else 20)
    device_sweeps = args.device_sweeps or (5 if quick else 30)
    presses = args.presses or (30 if quick else 200)
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    hosts = _hosts()
    result = {"quick": quick, "environment": _versions(),
              "load_average_1_5_15_min": {"start": os.getloadavg()}}
    t0 = time.perf_counter()

    if "rtde" not in skip:
        runs = []
        for busy in (int(b) for b in args.busy.split(",") if b.strip()):
            log(f"RTDE receive: {seconds:g} s with {busy} busy process(es)")
            runs.append(rtde_receive_run(next(hosts), seconds, busy, args.poll_ms))
        result["rtde_receive"] = runs
    if "trigger" not in skip:
        log(f"trigger to position: {sweeps} RTDE sweeps, {device_sweeps} device sweeps per speed")
        rows = rtde_trigger_sweeps(next(hosts), sweeps, seed=args.seed)
        rows += device_trigger_sweeps(device_sweeps, seed=args.seed)
        result["trigger_position"] = {"speeds_mm_s": list(SPEEDS_MM_S), "device_scan_s": DEVICE_SCAN_S,
                                      "rows": rows}
    if "panel" not in skip:
        log(f"panel: {presses} presses, polling every {args.panel_poll_ms:g} ms")
        result["panel"] = panel_latency(presses, args.panel_poll_ms / 1000.0, seed=args.seed)

    result["load_average_1_5_15_min"]["end"] = os.getloadavg()
    result["wall_seconds"] = time.perf_counter() - t0
    out = REPO / "bench" / "results"
    out.mkdir(exist_ok=True)
    (out / "drivers.json").write_text(json.dumps(result, indent=1, default=str) + "\n")

    if "rtde_receive" in result:
        print_rtde_table(result["rtde_receive"])
    if "trigger_position" in result:
        print_trigger_table(result["trigger_position"]["rows"])
    if "panel" in result:
        print_panel_table(result["panel"])
    print(f"\nwritten: {out / 'drivers.json'}  ({result['wall_seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
