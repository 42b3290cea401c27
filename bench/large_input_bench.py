"""Large measurement files: time and peak memory of ``cellcal identify`` and ``cellcal analyze``.

A tracker logging at 10 Hz through a shift writes ~300 000 rows (~50 MB). This bench
writes such files with ``cellcal sim-data`` (UR10e, compliance hidden at the elbow so
that ``analyze`` has something to name), then runs both commands on 10k, 30k, 100k and
300k rows as subprocesses and measures wall time, CPU time and peak RSS of each run
(``os.wait4``: the child's own rusage). The same runs are made, in the same bench run and
interleaved with ours, with the code of a baseline commit (``--baseline``): its tree is
taken with ``git archive`` into bench/results/ and run from there, installed nowhere.
The two answers are compared (training error, prior weight, noise, named cause, held-out
errors). Small problems (150 and 1000 rows) are timed in-process, solver calls only,
median of repeats, so that the interpreter's start-up does not hide a change.

    python -m bench.large_input_bench                       # everything, about 20 min on 2 cores
    python -m bench.large_input_bench --rows 10000,30000    # a quick look
    python -m bench.large_input_bench --no-baseline         # ours only

Progress goes to stderr, the table to stdout, every number to bench/results/large_input.json.
"""
from __future__ import annotations

import argparse
import io
import json
import os
import platform
import subprocess
import sys
import tarfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
DATA = RESULTS / "large"
AREAS = ("config", "daemon", "drivers", "routines", "sims", "solvers")
# the last commit before identify/analyze were made to work a block of rows at a time
BASELINE = "198df038877c4f1d8fe0743af24e247075668b08"
ROBOT = "ur10e"
EFFECT = "joint_compliance:2"
THREADS = {v: "1" for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}

SMALL = r"""
import json, sys, time
import numpy as np
from threadpoolctl import threadpool_limits
from cellcal.config.robot_files import load_robot
from cellcal.measurements.reader import read_measurements
from cellcal.solvers.analysis.analyze import analyze
from cellcal.solvers.analysis.effects import Context, approach_directions
from cellcal.solvers.identification.identify import identify
model = load_robot(sys.argv[2])
table = read_measurements(sys.argv[1], model.n_joints)
obs = table.observations()
ctx = Context(direction=approach_directions(table.q_rad), t_s=table.t_s, temp_c=table.temp_c)
out = {}
with threadpool_limits(limits=1, user_api="blas"):
    for name, call in (("identify", lambda: identify(model, obs)), ("analyze", lambda: analyze(model, obs, ctx))):
        cpu = []
        for _ in range(int(sys.argv[3])):
            t0 = time.process_time()
            call()
            cpu.append(time.process_time() - t0)
        out[name] = float(np.median(cpu))
print(json.dumps(out))
"""


def say(msg: str) -> None:
    print(f"[large-input-bench] {msg}", file=sys.stderr, flush=True)


def package_tree(src: Path, dest: Path) -> Path:
    """A folder that makes `cellcal` importable from the areas in src (symlinks; nothing installed)."""
    pkg = dest / "cellcal"
    pkg.mkdir(parents=True, exist_ok=True)
    (pkg / "__init__.py").touch()
    for area in AREAS:
        link = pkg / area
        if link.is_symlink() or link.exists():
            link.unlink()
        link.symlink_to(src / area, target_is_directory=True)
    return dest


def baseline_tree(rev: str) -> Path:
    """A commit's files, from git archive, laid out as the package."""
    rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", rev], check=True, capture_output=True,
                         text=True).stdout.strip()
    out = RESULTS / f"tree-{rev[:12]}"
    src = out / "src"
    if not (src / "solvers").exists():
        say(f"extracting {rev[:12]} with git archive")
        tar = subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", rev], check=True,
                             capture_output=True).stdout
        src.mkdir(parents=True, exist_ok=True)
        with tarfile.open(fileobj=io.BytesIO(tar)) as archive:
            archive.extractall(src, filter="data")
    return package_tree(src.resolve(), out / "pkg")


def data_file(rows: int) -> Path:
    path = DATA / f"{ROBOT}_{EFFECT.replace(':', '')}_{rows}.csv"
    if not path.exists():
        DATA.mkdir(parents=True, exist_ok=True)
        say(f"writing {path.name} with cellcal sim-data")
        subprocess.run([sys.executable, "-m", "cellcal.cli.main", "sim-data", "--robot", ROBOT, "--poses",
                        str(rows), "--effect", EFFECT, "--seed", "1", "-o", str(path)],
                       check=True, env=_env(package_tree(ROOT, RESULTS / "current-pkg")), stdout=subprocess.DEVNULL)
    return path


def _env(pythonpath: Path) -> dict:
    return {**os.environ, **THREADS, "PYTHONPATH": str(pythonpath)}


def run_command(pkg: Path, command: str, data: Path, tag: str) -> dict:
    """One CLI run as a child process: wall and CPU seconds, peak RSS, and its JSON answer."""
    out_path = RESULTS / f"large-{tag}-{command}-{data.stem}.json"
    with open(out_path, "wb") as out, open(os.devnull, "wb") as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "cellcal.cli.main", command, "--robot", ROBOT,
                                 "--data", str(data), "--json"], stdout=out, stderr=err, env=_env(pkg))
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    answer = json.loads(out_path.read_text() or "{}")
    return {"exit": proc.returncode, "wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime,
            "peak_mb": usage.ru_maxrss / 1024.0, "answer": summary(command, answer)}


def summary(command: str, doc: dict) -> dict:
    """The numbers of an answer that must not change."""
    if "error" in doc or not doc:
        return {"error": doc.get("error")}
    if command == "identify":
        return {"train_mean_mm": doc["train"]["mean_mm"], "lambda": doc["regularize"]["lambda"],
                "noise_mm": doc["noise_mm"], "structural_rank": doc["structural_rank"],
                "held": [p["name"] for p in doc["parameters"] if p["held"]]}
    return {"cause": doc["cause"], "where": doc["where"], "baseline_mm": doc["baseline"]["heldout_mean_mm"],
            "extended_mm": doc["extended"]["heldout_mean_mm"], "gain_pct": doc["gain_pct"],
            "magnitude": doc["magnitude"]}


def agree(command: str, a: dict, b: dict) -> str:
    """How far two answers are apart, in words."""
    if "error" in a or "error" in b:
        return "error" if a != b else "same error"
    if command == "identify":
        rel = abs(a["train_mean_mm"] - b["train_mean_mm"]) / a["train_mean_mm"]
        same = a["lambda"] == b["lambda"] and a["structural_rank"] == b["structural_rank"]
        held = "" if a["held"] == b["held"] else f"; held {','.join(b['held'])} (was {','.join(a['held'])})"
        return f"{'same' if same else 'DIFFERENT'} lambda/rank, train mean {rel:.1e} rel{held}"
    rel = max(abs(a[k] - b[k]) / abs(a[k]) for k in ("baseline_mm", "extended_mm"))
    same = a["cause"] == b["cause"] and a["where"] == b["where"]
    return f"{'same' if same else 'DIFFERENT'} cause, held-out means {rel:.1e} rel"


def small_problems(pkgs: dict, sizes, repeats: int) -> dict:
    out = {}
    for rows in sizes:
        data = data_file(rows)
        for tag, pkg in pkgs.items():
            say(f"small problem: {rows} rows, {tag}")
            done = subprocess.run([sys.executable, "-c", SMALL, str(data), ROBOT, str(repeats)], check=True,
                                  capture_output=True, text=True, env=_env(pkg))
            out.setdefault(str(rows), {})[tag] = json.loads(done.stdout.strip().splitlines()[-1])
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", default="10000,30000,100000,300000", help="file sizes, comma separated")
    parser.add_argument("--small", default="150,1000", help="small sizes timed in-process ('' for none)")
    parser.add_argument("--repeats", type=int, default=5, help="repeats of each small-problem solve (median)")
    parser.add_argument("--baseline", default=BASELINE, help="commit to compare against")
    parser.add_argument("--no-baseline", action="store_true", help="measure this tree only")
    parser.add_argument("--current", metavar="COMMIT",
                        help="measure this commit (from git archive) instead of the working tree")
    args = parser.parse_args(argv)
    sizes = [int(r) for r in args.rows.split(",") if r]
    pkgs = {"after": baseline_tree(args.current) if args.current else package_tree(ROOT, RESULTS / "current-pkg")}
    if not args.no_baseline:
        pkgs = {"before": baseline_tree(args.baseline), **pkgs}
    load_start = os.getloadavg()
    runs: dict = {}
    for rows in sizes:
        data = data_file(rows)
        for command in ("identify", "analyze"):
            for tag, pkg in pkgs.items():
                say(f"{command}, {rows} rows, {tag}")
                r = run_command(pkg, command, data, tag)
                runs.setdefault(str(rows), {}).setdefault(command, {})[tag] = r
                say(f"  {r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s CPU, {r['peak_mb']:.0f} MB peak, exit {r['exit']}")
    small = small_problems(pkgs, [int(r) for r in args.small.split(",") if r], args.repeats) if args.small else {}
    doc = {"baseline": None if args.no_baseline else args.baseline, "current": args.current or "working tree",
           "robot": ROBOT, "effect": EFFECT,
           "runs": runs, "small_cpu_s": small, "loadavg_start": load_start, "loadavg_end": os.getloadavg(),
           "python": platform.python_version(), "cpus": os.cpu_count(), "threads": THREADS}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "large_input.json").write_text(json.dumps(doc, indent=1) + "\n")
    print_table(doc, list(pkgs))
    return 0


def print_table(doc: dict, tags: list[str]) -> None:
    both = tags == ["before", "after"]
    print(f"\n{doc['robot']}, hidden {doc['effect']}; wall and CPU seconds, peak RSS in MB "
          f"(load average {doc['loadavg_start'][0]:.1f} at the start, {doc['loadavg_end'][0]:.1f} at the end)\n")
    head = f"{'rows':>7s} {'command':9s}"
    for tag in tags:
        head += f" | {tag + ' wall':>11s} {'CPU':>7s} {'peak MB':>8s}"
    if both:
        head += f" | {'CPU ratio':>9s} {'mem ratio':>9s}  answers"
    print(head)
    print("-" * len(head))
    for rows, commands in doc["runs"].items():
        for command, by_tag in commands.items():
            line = f"{int(rows):7d} {command:9s}"
            for tag in tags:
                r = by_tag[tag]
                line += f" | {r['wall_s']:11.1f} {r['cpu_s']:7.1f} {r['peak_mb']:8.0f}"
            if both:
                b, a = by_tag["before"], by_tag["after"]
                line += (f" | {b['cpu_s'] / a['cpu_s']:8.1f}x {b['peak_mb'] / a['peak_mb']:8.1f}x  "
                         f"{agree(command, b['answer'], a['answer'])}")
            print(line)
    print("\nGrowth (ours): peak memory and CPU time against the previous size")
    sizes = list(doc["runs"])
    for command in ("identify", "analyze"):
        for prev, cur in zip(sizes, sizes[1:]):
            p, c = doc["runs"][prev][command]["after"], doc["runs"][cur][command]["after"]
            added_mb = c["peak_mb"] - p["peak_mb"]
            print(f"  {command:9s} {int(prev):7d} -> {int(cur):7d} rows (x{int(cur) / int(prev):.1f}): memory "
                  f"+{added_mb:.0f} MB ({1e3 * added_mb / (int(cur) - int(prev)):.2f} kB per added row), "
                  f"CPU x{c['cpu_s'] / p['cpu_s']:.2f}")
    if doc["small_cpu_s"]:
        print("\nSmall problems, solver CPU seconds in-process (median)")
        for rows, by_tag in doc["small_cpu_s"].items():
            for command in ("identify", "analyze"):
                cells = "  ".join(f"{tag} {by_tag[tag][command]:.3f}" for tag in tags)
                ratio = f"  after/before {by_tag['after'][command] / by_tag['before'][command]:.2f}" if both else ""
                print(f"  {int(rows):5d} rows {command:9s} {cells}{ratio}")


if __name__ == "__main__":
    sys.exit(main())
