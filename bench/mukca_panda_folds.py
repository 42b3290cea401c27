"""Leave-one-placement-out calibration of a Franka Panda on the socket-plate data set of Franzese, Spahn, Ramirez
et al., "MUKCa: Accurate and Affordable Cobot Calibration Without External Measurement Devices" (joint angles only,
a ball seated by hand in two sockets 50 mm apart; see the data set's README).

For each robot folder (``panda_3``, ``panda_4``) and each placement in it, the placement is held out: the others are
imported into CAL.csv, it into VAL.csv (``cellcal import mukca``), and

    cellcal identify --robot franka-panda --data CAL.csv --fixture bench/mukca_plate.yaml --validate VAL.csv --json

calibrates on CAL and places the plate anew at VAL's placement (its two sockets fitted to VAL's seatings with the
known 50 mm, the arm as calibrated); ``validate.mean_mm`` is the mean distance of VAL's seatings from their sockets.
The same for the nominal arm is ``before.validate_mean_mm``. Nothing here is tuned to the data: the robot file is
Franka's table, the fixture file the plate's stated distance and tolerance, every option cellcal's default.

    python -m bench.mukca_panda_folds                                  # both robots, ~20 s
    python -m bench.mukca_panda_folds --data ../shared/data/mukca-panda --robots panda_3

Each fold runs as the command line does, one process at a time. Results: bench/results/mukca-panda-folds.json.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
CELLCAL = [sys.executable, "-m", "cellcal.cli"]


def cellcal(*args: str) -> str:
    run = subprocess.run([*CELLCAL, *args], capture_output=True, text=True)
    if run.returncode not in (0, 1):
        raise SystemExit(f"cellcal {' '.join(args)}: exit {run.returncode}\n{run.stderr}")
    return run.stdout


def fold(robot_dir: Path, held: str, fixture: Path, tmp: Path) -> dict:
    others = [str(p) for p in sorted(robot_dir.iterdir()) if p.is_dir() and p.name != held]
    cal, val = tmp / f"{robot_dir.name}-without-{held}.csv", tmp / f"{robot_dir.name}-{held}.csv"
    cellcal("import", "mukca", *others, "-o", str(cal))
    cellcal("import", "mukca", str(robot_dir / held), "-o", str(val))
    doc = json.loads(cellcal("identify", "--robot", "franka-panda", "--data", str(cal), "--fixture", str(fixture),
                             "--validate", str(val), "--json"))
    return {"robot": robot_dir.name, "held_out": held, "success": doc["success"],
            "train_mean_mm": doc["train"]["mean_mm"], "validate_mean_mm": doc["validate"]["mean_mm"],
            "validate_max_mm": doc["validate"]["max_mm"], "validate_rows": doc["validate"]["n"],
            "nominal_train_mean_mm": doc["before"]["train_mean_mm"],
            "nominal_validate_mean_mm": doc["before"]["validate_mean_mm"],
            "noise_mm": doc["noise_mm"], "structural_rank": doc["structural_rank"], "noise_rank": doc["noise_rank"],
            "held": [p["name"] for p in doc["parameters"] if p["held"]],
            "fitted_distances_mm": [d["fitted_mm"] for d in doc["fixture_distances"]]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=HERE.parent.parent / "shared" / "data" / "mukca-panda")
    ap.add_argument("--robots", nargs="+", default=["panda_3", "panda_4"])
    ap.add_argument("--fixture", type=Path, default=HERE / "mukca_plate.yaml")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "mukca-panda-folds.json")
    args = ap.parse_args(argv)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for robot in args.robots:
            robot_dir = args.data / robot
            for held in sorted(p.name for p in robot_dir.iterdir() if p.is_dir()):
                rows.append(fold(robot_dir, held, args.fixture, Path(tmp)))
                r = rows[-1]
                print(f"{robot:8s} held out {held:12s} validate {r['validate_mean_mm']:.3f} mm (max "
                      f"{r['validate_max_mm']:.3f}, {r['validate_rows']} rows)  nominal {r['nominal_validate_mean_mm']:.3f}"
                      f"  train {r['train_mean_mm']:.3f}  noise {r['noise_mm']:.3f}  ranks "
                      f"{r['structural_rank']}/{r['noise_rank']}", flush=True)
    summary = {}
    for robot in args.robots:
        mine = [r for r in rows if r["robot"] == robot]
        summary[robot] = {k: sum(r[k] for r in mine) / len(mine)
                          for k in ("validate_mean_mm", "nominal_validate_mean_mm", "train_mean_mm")}
        s = summary[robot]
        print(f"{robot:8s} average over {len(mine)} held-out placements: validate {s['validate_mean_mm']:.3f} mm, "
              f"nominal {s['nominal_validate_mean_mm']:.3f} mm, train {s['train_mean_mm']:.3f} mm")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"folds": rows, "average": summary}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
