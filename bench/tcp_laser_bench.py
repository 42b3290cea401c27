"""Bench: tcp-laser against the seed's light-barrier TCP calibration (Lin et al. 2023).

    python -m bench.tcp_laser_bench            # 3 speeds x 5 simulated cells
    python -m bench.tcp_laser_bench --seeds 2  # quicker

Both methods run in the same simulated cells (``config/cells/sim.yaml`` with other truth
seeds: tool up to 1 mm and 0.5 deg off its drawing, beams 0.5 mm off, 2.5 ms trigger
latency with +-0.5 ms jitter, 0.03 mm repeatability per motion), with the same noise draws
per cell, at 20, 40 and 100 mm/s, and are scored against the hidden truth.

The seed's method, as the paper describes it (its Sections 2.3-2.4 and Figure 8): the tool
upright, one sweep across each beam (along each beam's normal, one direction) at a first
height and at a second; the tool centre offset at each height from the midpoint of the
trigger positions; the runout angle from the offsets' change over the height difference
(Eq. 6); the preliminary offset extrapolated to the tip; the TCP set to that, the tool
turned upright on its corrected axis and swept again at the first height (the third plane)
for the final X and Y offset; last, a vertical approach from above, the tip's height at
the trigger taken as the beam's (plus its half width, which the paper does not model).
Positions are read at the trigger's timestamp with no latency correction. The station is
where the cell file says; a second row gives the same data the beams' true positions (a
station calibrated perfectly, as the paper's taught LATC station is assumed to be), an
upper bound on the method that isolates what the latency and one-way sweeps cost.

Ours: ``cellcal run tcp-laser`` with ``speed_mm_s`` set, through the routine runner; and
a short plan of three orientations (upright at two turns, one tilt) for a shorter cycle.
The table: mean and worst TCP position error (mm) and axis error (deg) over the cells,
cycle time (simulated seconds, motion under the cell's speed and acceleration limits),
and ours' error as a fraction of each baseline's. Every number to bench/results/tcp_laser.json.
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make `bench` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cellcal.config.robot_files import load_robot  # noqa: E402
from cellcal.daemon.cells import load_cell, open_drivers  # noqa: E402
from cellcal.routines.framework import runner  # noqa: E402
from cellcal.routines.framework.guard import GuardedRobot, MotionGuard  # noqa: E402
from cellcal.routines.framework.base import Move  # noqa: E402
from cellcal.solvers.geometry import se3  # noqa: E402
from cellcal.solvers.geometry.inverse import tcp_poses  # noqa: E402
from cellcal.solvers.tool_frames.tcp_laser import crossing_point  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SPEEDS_MM_S = (20.0, 40.0, 100.0)
SEEDS = (7, 11, 23, 37, 41)
SHORT_PLAN = {"spins_deg": [180, 0], "tilts": 1}  # ours with three orientations instead of six
HEIGHTS_MM = (20.0, 80.0)  # the seed's two planes, behind the tip
SWEEP_HALF_MM = 12.0  # each sweep from 12 mm before the beam to 12 mm past it
SIDE_MM = 15.0  # sweeps cross each beam this far along it from the crossing (clear of the other beam)
APPROACH_MM = 6.0


def log(msg: str) -> None:
    print(f"[tcp-laser-bench] {msg}", file=sys.stderr, flush=True)


def cell_for(seed: int, speed_mm_s: float, **options):
    cell = copy.deepcopy(load_cell("sim"))
    cell.sim_truth = dataclasses.replace(cell.sim_truth, seed=seed)
    cell.routines["tcp_laser"] = {**cell.routines.get("tcp_laser", {}), "speed_mm_s": speed_mm_s, **options}
    return cell


# -- ours ---------------------------------------------------------------------------------------

def run_ours(cell, noise_seed: int, out_dir: str) -> dict:
    prepared = runner.prepare("tcp-laser", cell)
    with open_drivers(cell) as drivers:
        drivers.world.rng = np.random.default_rng(noise_seed)
        dataset = runner.measure(prepared, drivers, out_dir, lambda message: None)
        truth = drivers.world.truth
    result = runner.solve("tcp-laser", cell, dataset)
    score = truth.score_tool_frame(result.tool_frame)
    return {"position_error_mm": score["position_error_mm"], "axis_error_deg": score["axis_error_deg"],
            "cycle_time_s": result.cycle_time_s, "latency_ms": result.extra["latency_ms"],
            "latency_std_ms": result.extra["latency_std_ms"], "true_latency_ms": truth.trigger_latency_s * 1e3,
            "passed_gates": result.passed_gates}


# -- the seed's method ------------------------------------------------------------------------------

class Station:
    """The seed's procedure on the cell's devices: moves through the guard, trigger
    positions from the state stream at the edges' timestamps (not corrected)."""

    def __init__(self, cell, drivers):
        self.cell, self.drivers = cell, drivers
        self.robot = GuardedRobot(drivers.robot, MotionGuard(cell, load_robot(cell.robot)))
        self.v_travel, self.accel = cell.limits["tcp_speed_m_s"], cell.limits["tcp_accel_m_s2"]

    def go(self, pose, speed=None):
        self.robot.run(Move.linear("seed method", pose, speed or self.v_travel, self.accel))

    def sweep(self, start, end, speed) -> list[tuple[int, str, np.ndarray]]:
        """Travel to `start`, sweep to `end`; (channel, edge, TCP position at the stamp) of its edges."""
        self.go(start)
        self.drivers.trigger.events(0.0)
        t0 = self.robot.samples()[-1].t_s
        self.go(end, speed)
        events = self.drivers.trigger.events(0.05)
        samples = self.robot.samples(t0 - 1e-9)
        t = np.array([s.t_s for s in samples])
        p = np.array([s.tcp_pose[:3] for s in samples])
        return [(e.channel, e.edge.value, np.array([np.interp(e.t_s, t, p[:, j]) for j in range(3)]))
                for e in events if t0 < e.t_s]


def seed_method(cell, noise_seed: int, speed_mm_s: float) -> dict:
    """The seed's procedure in one simulated cell; the error of its result with the station
    where the cell file says and with the station's true position."""
    tool, beams = cell.tool, cell.beams
    speed = speed_mm_s / 1e3
    dirs = [b.direction / np.linalg.norm(b.direction) for b in beams]
    normals = [np.cross([0.0, 0.0, 1.0], d) / np.linalg.norm(np.cross([0.0, 0.0, 1.0], d)) for d in dirs]
    cross = crossing_point([b.point_m for b in beams], dirs)
    with open_drivers(cell) as drivers:
        drivers.world.rng = np.random.default_rng(noise_seed)
        truth = drivers.world.truth
        stations = {"nominal": [b.point_m for b in beams], "calibrated": [b.point_m for b in truth.beams]}
        station = Station(cell, drivers)
        robot = station.robot
        robot.set_tcp(tool.tcp_pose)
        t_start = robot.samples()[-1].t_s
        home = tcp_poses(load_robot(cell.robot), cell.home_q_rad, tool.tcp_pose)[0]
        rot_tcp = se3.rotvec_to_matrix(home[3:])  # upright: the tool frame's z straight down
        u = rot_tcp[:, 2]
        above = np.r_[cross - APPROACH_MM / 1e3 * u, home[3:]]

        def plane(h_mm) -> list[dict]:
            """One sweep across each beam at height h (clear of the other beam): the midpoint of
            the TCP positions at entry and exit."""
            found = []
            for k in range(len(beams)):
                centre = cross + SIDE_MM / 1e3 * dirs[k] + h_mm / 1e3 * u
                start = np.r_[centre - SWEEP_HALF_MM / 1e3 * normals[k], home[3:]]
                end = np.r_[centre + SWEEP_HALF_MM / 1e3 * normals[k], home[3:]]
                edges = [p for ch, _, p in station.sweep(start, end, speed) if ch == beams[k].channel]
                if len(edges) != 2:
                    raise RuntimeError(f"seed method: sweep across beam {k} at {h_mm} mm saw {len(edges)} edges")
                found.append({"k": k, "mid": 0.5 * (edges[0] + edges[1]), "h": h_mm / 1e3})
            station.go(above)  # up and clear
            return found

        def offset(found, points) -> np.ndarray:
            """The real axis' horizontal offset from the TCP's line at the plane's height (base frame)."""
            return sum(((points[f["k"]] - (f["mid"] - f["h"] * u)) @ normals[f["k"]]) * normals[f["k"]]
                       for f in found)

        station.go(above)
        planes = [plane(h) for h in HEIGHTS_MM]
        # runout (Eq. 6) and the preliminary offset, on the station as the cell file has it
        rot_flange = rot_tcp @ se3.rotvec_to_matrix(tool.tcp_pose[3:]).T
        d1, d2 = offset(planes[0], stations["nominal"]), offset(planes[1], stations["nominal"])
        slope = (d2 - d1) / ((HEIGHTS_MM[1] - HEIGHTS_MM[0]) / 1e3)  # shift per metre back from the tip
        axis_base = (u - slope) / np.linalg.norm(u - slope)
        tip = tool.tcp_m + rot_flange.T @ (d1 - HEIGHTS_MM[0] / 1e3 * slope)
        first = np.concatenate([tip, se3.rotvec_from_z(rot_flange.T @ axis_base)])
        # the third plane with the corrected axis upright, then the vertical approach
        robot.set_tcp(first)
        station.go(above)
        third = plane(HEIGHTS_MM[0])
        edges = station.sweep(above, np.r_[cross + APPROACH_MM / 1e3 * u, home[3:]], speed)
        blocked = [p for _, e, p in edges if e == "blocked"]
        if len(blocked) != len(beams):
            raise RuntimeError(f"seed method: the approach saw {len(blocked)} blocked edges")
        trigger_tcp = np.mean(blocked, axis=0)
        cycle = robot.samples()[-1].t_s - t_start
    flange_rot = rot_tcp @ se3.rotvec_to_matrix(first[3:]).T
    flange_pos = trigger_tcp - flange_rot @ first[:3]
    results = {}
    for label, points in stations.items():
        # the axis is upright now: the third plane's offset is the tip's; its height is the beams'
        lateral = offset(third, points)
        beam_z = np.mean([p[2] for p in points]) + np.mean([b.radius_m for b in beams])
        tip_base = np.r_[trigger_tcp[:2] + lateral[:2], beam_z]
        frame = np.concatenate([flange_rot.T @ (tip_base - flange_pos), first[3:]])
        score = truth.score_tool_frame(frame)
        results[label] = {"position_error_mm": score["position_error_mm"],
                          "axis_error_deg": score["axis_error_deg"], "cycle_time_s": cycle,
                          "tool_frame": frame.tolist()}
    return results


# -- the table ------------------------------------------------------------------------------------

def summary(rows: list[dict]) -> dict:
    pos = np.array([r["position_error_mm"] for r in rows])
    ax = np.array([r["axis_error_deg"] for r in rows])
    return {"position_mean_mm": float(pos.mean()), "position_max_mm": float(pos.max()),
            "axis_mean_deg": float(ax.mean()), "axis_max_deg": float(ax.max()),
            "cycle_time_s": float(np.mean([r["cycle_time_s"] for r in rows]))}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=len(SEEDS), help="how many simulated cells per speed")
    args = parser.parse_args(argv)
    seeds = list(SEEDS[:args.seeds]) + list(range(100, 100 + max(0, args.seeds - len(SEEDS))))
    out = {"speeds_mm_s": list(SPEEDS_MM_S), "seeds": seeds, "runs": []}
    table = []
    with tempfile.TemporaryDirectory() as tmp:
        for speed in SPEEDS_MM_S:
            per = {"ours": [], "ours, short plan (3 orientations)": [], "seed, station as in the cell file": [],
                   "seed, station calibrated": []}
            for seed in seeds:
                cell = cell_for(seed, speed)
                ours = run_ours(cell, 1000 + seed, tmp)
                short = run_ours(cell_for(seed, speed, **SHORT_PLAN), 1000 + seed, tmp)
                base = seed_method(cell, 1000 + seed, speed)
                per["ours"].append(ours)
                per["ours, short plan (3 orientations)"].append(short)
                per["seed, station as in the cell file"].append(base["nominal"])
                per["seed, station calibrated"].append(base["calibrated"])
                out["runs"].append({"speed_mm_s": speed, "seed": seed, "ours": ours, "ours_short": short,
                                    "seed_method": base})
                log(f"{speed:g} mm/s, cell {seed}: ours {ours['position_error_mm']:.4f} / "
                    f"{short['position_error_mm']:.4f} mm, "
                    f"seed {base['nominal']['position_error_mm']:.3f} / {base['calibrated']['position_error_mm']:.3f} mm")
            for name, rows in per.items():
                table.append({"speed_mm_s": speed, "method": name, **summary(rows)})
    ours_by_speed = {t["speed_mm_s"]: t for t in table if t["method"] == "ours"}
    print(f"{'speed':>6}  {'method':<36} {'TCP mean':>9} {'TCP max':>8} {'axis mean':>10} {'axis max':>9} "
          f"{'cycle':>7} {'ours/it':>8}")
    for t in table:
        ratio = ours_by_speed[t["speed_mm_s"]]["position_mean_mm"] / t["position_mean_mm"]
        t["ours_position_ratio"] = ratio
        print(f"{t['speed_mm_s']:>4g}/s  {t['method']:<36} {t['position_mean_mm']:8.4f}mm {t['position_max_mm']:7.4f}mm "
              f"{t['axis_mean_deg']:8.4f}deg {t['axis_max_deg']:7.4f}deg {t['cycle_time_s']:6.1f}s {ratio:8.3f}")
    out["table"] = table
    results = REPO / "bench" / "results"
    results.mkdir(parents=True, exist_ok=True)
    (results / "tcp_laser.json").write_text(json.dumps(out, indent=1, default=float))
    log(f"wrote {results / 'tcp_laser.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
