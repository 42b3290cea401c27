"""``cellcal compensate --program`` on a long program: time and peak memory against the code before
its array path (``bench/program_before.py``), measured in the same run on the same program and models.

The program (``tests/support/programs.py``, ``long_program``): 50 000 lines by default, stations of
5 to 80 targets each (``movel`` poses mostly, ``movep``, ``movec``, a ``movej`` to joints every 16th,
every 10th computed at run time, every 20th station under a tool set at run time), four tools in
turn, the joints a random walk that stays within a window about a home configuration (inside the
joint limits, clear of singular configurations). The models: a UR10e calibrated by ``analyze`` from
250 simulated tracker positions with a hidden joint-2 compliance (the ``compliance`` model, the
effect applied), and the same geometry without the effect (``rigid``).

Each measurement is a fresh Python process (so imports and start-up count, as for the command):

``before`` / ``after``
    read the program, compensate it (``compensate_program``), rewrite it and write it: the old
    code (``bench/program_before.py``) and the package's;
``command``
    the whole command, ``cellcal compensate --program ... --allow-partial --json`` (after only).

Reported per model: wall time of the process, peak resident memory (the process' own
``ru_maxrss``), the ratio before / after, and whether the command meets 5 s and 300 MB. The
statuses of every target must be the same before and after and every compensated value the same
to 1e-10 (m and rad: the solvers stop at 1e-7 mm and 1e-10 rad), else the bench fails. Results
go to ``bench/results/program.json``; programs and models to ``bench/results/program/``.

    python -m bench.program_bench                   # 50 000 lines, both models, ~1 min
    python -m bench.program_bench --lines 5000 --models compliance
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "results"
MODELS = ("rigid", "compliance")
TARGET_S, TARGET_MB = 5.0, 300.0  # for 50 000 lines
SAME = 1e-10  # m and rad: the solvers' own tolerance (1e-7 mm, 1e-10 rad); see the module docstring


def prepare(folder: Path, lines: int, seed: int) -> Path:
    """The models (cal-rigid.yaml, cal-compliance.yaml) and the program prog.script in `folder`."""
    sys.path.insert(0, str(ROOT / "tests"))
    from support.programs import calibrated_with_compliance, long_program  # a test helper, not in the package

    from cellcal.config.model_files import write_calibrated
    from cellcal.config.robot_files import load_robot
    from cellcal.solvers.compensation.calibrated_model import from_fit

    folder.mkdir(parents=True, exist_ok=True)
    model = load_robot("ur10e")
    compliance, _ = calibrated_with_compliance(model, seed=seed)
    rigid = from_fit(model, compliance.target_names, compliance.x)
    write_calibrated(folder / "cal-compliance.yaml", compliance, "ur10e", {"written_by": "bench/program_bench.py"})
    write_calibrated(folder / "cal-rigid.yaml", rigid, "ur10e", {"written_by": "bench/program_bench.py"})
    program = folder / "prog.script"
    program.write_text(long_program(model, compliance.offsets[0], lines=lines, seed=seed))
    return program


def child(which: str, model_file: str, program_file: str, out: str) -> None:
    """One measurement in this process (module docstring); prints its own seconds and peak memory as JSON
    and, for before/after, writes every target's status and values to OUT.json."""
    started = time.perf_counter()
    if which == "command":
        from cellcal.cli.main import main
        with open(os.devnull, "w") as null:
            stdout, sys.stdout = sys.stdout, null
            try:
                code = main(["compensate", "--robot", model_file, "--program", program_file, "-o", out,
                             "--allow-partial", "--json"])
            finally:
                sys.stdout = stdout
        print(json.dumps({"seconds": time.perf_counter() - started, "code": code, "peak_mb": _peak_mb()}))
        return
    from cellcal.config.model_files import load_calibrated, source_model
    from cellcal.config.robot_files import load_robot
    if which == "before":
        from bench.program_before import compensate_program, encode, read_program, rewrite
    else:
        from cellcal.programs.apply import compensate_program
        from cellcal.programs.urscript import encode, read_program, rewrite
    calibrated = load_calibrated(model_file)
    nominal = load_robot(source_model(model_file))
    program = read_program(program_file)
    result = compensate_program(program, nominal, calibrated, default_tcp_mm=calibrated.offsets[0])
    with open(out, "wb") as f:
        f.write(encode(rewrite(program.text, result.replacements)))
    seconds, peak = time.perf_counter() - started, _peak_mb()
    with open(out + ".json", "w") as f:
        json.dump([[o.status, o.values] for o in result.per_target], f)
    print(json.dumps({"seconds": seconds, "compensate_s": result.seconds, "peak_mb": peak,
                      "targets": len(result.per_target)}))


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux


def measure(which: str, model_file: Path, program: Path, out: Path) -> dict:
    """Run one measurement in a fresh process: its wall time as seen from here, and what it reports."""
    t0 = time.perf_counter()
    run = subprocess.run([sys.executable, "-m", "bench.program_bench", "--child", which, str(model_file),
                          str(program), str(out)], cwd=ROOT, capture_output=True, text=True,
                         env={**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
                              "MKL_NUM_THREADS": "1"})
    wall = time.perf_counter() - t0
    if run.returncode != 0:
        raise SystemExit(f"{which} on {model_file.name} failed:\n{run.stderr}")
    return {"wall_s": wall, **json.loads(run.stdout.strip().splitlines()[-1])}


def same_answer(before: Path, after: Path) -> dict:
    """Statuses equal target by target, and the largest difference of the compensated values."""
    a, b = json.loads(before.read_text()), json.loads(after.read_text())
    statuses = len(a) == len(b) and all(x[0] == y[0] for x, y in zip(a, b))
    diff = max((float(np.abs(np.subtract(x[1], y[1])).max()) for x, y in zip(a, b) if x[1] and y[1]), default=0.0)
    counts = {s: sum(1 for x in b if x[0] == s) for s in sorted({x[0] for x in b})}
    return {"statuses_equal": statuses, "max_value_diff": diff, "statuses": counts}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lines", type=int, default=50_000, help="program length (default 50000)")
    ap.add_argument("--models", nargs="+", choices=MODELS, default=list(MODELS))
    ap.add_argument("--seed", type=int, default=5, help="the campaign's and the program's seed")
    ap.add_argument("--child", nargs=4, metavar=("WHICH", "MODEL", "PROGRAM", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(*args.child)
        return 0
    folder = OUT / "program"
    program = prepare(folder, args.lines, args.seed)
    lines = program.read_text().count("\n")
    print(f"program bench: {program.relative_to(ROOT)}, {lines} lines; each row a fresh process (wall time, "
          "peak resident memory)", flush=True)
    print(f"{'model':12s}{'code':>9s}{'wall s':>9s}{'compensate s':>14s}{'peak MB':>9s}{'x faster':>10s}"
          f"{'x less memory':>15s}")
    rows, good = {}, True
    for name in args.models:
        model_file = folder / f"cal-{name}.yaml"
        r = {w: measure(w, model_file, program, folder / f"out-{name}-{w}.script")
             for w in ("before", "after", "command")}
        r["check"] = same_answer(folder / f"out-{name}-before.script.json", folder / f"out-{name}-after.script.json")
        for w in ("before", "after", "command"):
            m = r[w]
            ratio = f"{r['before']['wall_s'] / m['wall_s']:10.1f}{r['before']['peak_mb'] / m['peak_mb']:15.1f}" \
                if w != "before" else ""
            print(f"{name:12s}{w:>9s}{m['wall_s']:9.2f}{m.get('compensate_s', float('nan')):14.2f}"
                  f"{m['peak_mb']:9.0f}{ratio}")
        c = r["check"]
        met = r["command"]["wall_s"] <= TARGET_S and r["command"]["peak_mb"] <= TARGET_MB
        same = c["statuses_equal"] and c["max_value_diff"] <= SAME
        r["targets_met"] = met
        good &= same and (met or args.lines != 50_000)
        print(f"{'':12s}statuses {c['statuses']}; the same before and after: {c['statuses_equal']}, values to "
              f"{c['max_value_diff']:.1e} (<= {SAME:g}: {same}); command within {TARGET_S:g} s and {TARGET_MB:g} MB: "
              f"{met}" + ("" if args.lines == 50_000 else " (the targets are for 50 000 lines)"))
        rows[name] = r
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "program.json").write_text(json.dumps({
        "lines": lines, "seed": args.seed, "targets": {"seconds": TARGET_S, "peak_mb": TARGET_MB}, "models": rows,
        "environment": {"python": platform.python_version(), "numpy": np.__version__, "cpus": os.cpu_count(),
                        "load_average": os.getloadavg()}}, indent=1))
    print(f"results: {(OUT / 'program.json').relative_to(ROOT)}")
    return 0 if good else 1


if __name__ == "__main__":
    raise SystemExit(main())
