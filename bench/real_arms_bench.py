"""Bench: ``cellcal analyze`` on the measured arms beside the repository, as a user runs it.

    python -m bench.real_arms_bench                      # UR10 series A and B, Agile Justin (~40 s)
    python -m bench.real_arms_bench --data ../shared/data --only ur10-B

Each data set runs as the command line does (``cellcal analyze --robot R --data D.csv --json``, every option
the default), one process at a time; the CPU time is the child's own (user + system). Printed per data set:
the held-out mean error of the geometric model (the baseline every finding is measured against, scored in the
same run on the same folds), of the named effect, and of the pair when a second effect is found; the finding;
the CPU seconds. Agile Justin's CPU time is set against its budget (BUDGET_S). The data sets:

- ``ur10-A``, ``ur10-B``: a UR10 measured with a laser tracker (``ipa-ur10/series_A.csv``, ``series_B.csv``:
  11 911 and 1 495 poses), the robot file ``ur10``;
- ``justin``: the humanoid Agile Justin (``dlr-agile-justin/measurements.csv``, imported with
  ``cellcal import dlr-justin``), the robot file ``agile-justin``.

Nothing is tuned to these data: every threshold is the analysis' own. Results: bench/results/real-arms.json.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
BUDGET_S = 10.0  # Agile Justin's analysis, CPU seconds
SETS = {
    "ur10-A": ("ur10", "ipa-ur10/series_A.csv", None),
    "ur10-B": ("ur10", "ipa-ur10/series_B.csv", None),
    "justin": ("agile-justin", "dlr-agile-justin/measurements.csv", "dlr-justin"),
}


def _cellcal(*args: str) -> tuple[str, float]:
    """(stdout, CPU seconds of the child) of one ``cellcal`` command; exits with its message when it fails."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run([sys.executable, "-m", "cellcal.cli", *args], capture_output=True, text=True,
                          env={**os.environ, "PYTHONWARNINGS": "ignore"})
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        sys.exit(f"cellcal {' '.join(args)} failed ({done.returncode}): {done.stderr.strip()}")
    return done.stdout, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def run(name: str, data: Path, workdir: Path) -> dict:
    robot, path, importer = SETS[name]
    csv = data / path
    if not csv.exists():
        return {"data": name, "missing": str(csv)}
    if importer is not None:
        imported = workdir / f"{name}.csv"
        _cellcal("import", importer, str(csv), "-o", str(imported))
        csv = imported
    out, cpu_s = _cellcal("analyze", "--robot", robot, "--data", str(csv), "--json")
    doc = json.loads(out)
    row = {"data": name, "robot": robot, "n": doc["n"], "cause": doc["cause"], "where": doc["where"],
           "geometry_mm": doc["baseline"]["heldout_mean_mm"], "effect_mm": doc["extended"]["heldout_mean_mm"],
           "cpu_s": cpu_s}
    if doc.get("second"):
        row["second"] = doc["second"]["label"]
        row["both_mm"] = doc["both"]["heldout_mean_mm"]
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=HERE.parents[1] / "shared" / "data",
                   help="the folder holding ipa-ur10/ and dlr-agile-justin/ (default: ../shared/data)")
    p.add_argument("--only", choices=tuple(SETS), action="append", help="run only this data set (repeatable)")
    p.add_argument("--out", type=Path, default=HERE / "results" / "real-arms.json")
    args = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.only or SETS:
            row = run(name, args.data, Path(tmp))
            rows.append(row)
            if "missing" in row:
                print(f"{name:8s} not run: {row['missing']} is not there")
                continue
            pair = f", with {row['second']} {row['both_mm']:.4f}" if "second" in row else ""
            budget = f" ({row['cpu_s'] / BUDGET_S:.2f} of its {BUDGET_S:.0f} s budget)" if name == "justin" else ""
            print(f"{name:8s} {row['n']:6d} poses  held-out mean: geometry {row['geometry_mm']:.4f} mm, "
                  f"{row['cause']} {row['effect_mm']:.4f} mm{pair}  [{row['cpu_s']:.1f} s CPU{budget}]")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
