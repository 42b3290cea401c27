"""Speed of ``identify --fixture`` and ``analyze --fixture`` on a large point-form campaign, against the code
before the points were eliminated block by block, measured in the same run; and the agreement of the two.

The campaign (``tests/support/point_data.py: campaign``): a UR10e with hidden geometric errors seats its
target ``--per-socket`` times (8) in both sockets of a 200 mm bar at ``--setups`` placements (100: 1600
rows, 200 unknown points, 100 known distances). The baseline is the commit ``--base`` (the last one before
the change), unpacked by ``git archive`` into a temporary folder; both codes run as the command line does
(``cellcal identify|analyze --robot ur10e --data D.csv --fixture F.yaml --json``), each in a process of its
own, one at a time, BLAS single-threaded (as the command line limits it). Reported per command and code:
wall time of the process (imports included, about 0.7 s), the command's own ``seconds``, peak resident
memory (the process' maxrss), and new / old ratios; the targets (identify <= 5 s, analyze <= 20 s at 100
setups) are marked met or not.

Agreement, on the timed campaign and on ``--check`` campaigns (a periodic error hidden at joint 5; stylus
balls): old and new must give the same held parameters and ranks, every estimate within a tolerance of its
standard deviation, the same named cause, and the same held-out means. Both fits stop within a relative
ftol = 1e-12 of the least-squares minimum's cost 0.5 s^2 dof; an estimate delta standard deviations off
the minimum raises that cost by 0.5 delta^2 s^2, so each fit is within sqrt(2 ftol dof) standard
deviations of it, and the two within DELTA = 2 sqrt(2 ftol dof) of each other. Held-out errors are
residuals of such fits: they agree to DELTA relative. Candidates that gain nothing over geometry alone
(held-out mean the baseline's within that tolerance) may be named by another place: the old code's
selection held point columns with few training rows as if they had none when a candidate's own columns
were 1e12 times larger (``selection.EMPTY_RTOL``), so its choice among places that all gain nothing
differed from the one with every point estimated; such differences are listed, not failed.

    python -m bench.fixture_speed_bench                       # 100 setups timed, two check campaigns; ~3 min
    python -m bench.fixture_speed_bench --setups 50 --no-check
    python -m bench.fixture_speed_bench --base <commit>       # another baseline

Results: bench/results/fixture-speed-<setups>.json (every timing, memory, difference and the environment).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if __package__ in (None, ""):
    sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))  # the campaign generator of the tests
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

from support.point_data import campaign  # noqa: E402

BASE = "9a240ae5b02c3091f65202e03431d18838b8d368"  # the last commit with the dense point-form solver
AREAS = ("cli", "config", "daemon", "drivers", "measurements", "programs", "reports", "routines", "sims", "solvers")
TARGET_S = {"identify": 5.0, "analyze": 20.0}  # at 100 setups
FTOL = 1e-12  # of every point-form fit, old and new


def package_view(tree: Path, into: Path) -> Path:
    """A folder whose ``cellcal`` package is the areas of `tree` (as pyproject's package-dir maps them): put
    first on PYTHONPATH, it is imported instead of the installed cellcal."""
    pkg = into / "cellcal"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    for area in AREAS:
        (pkg / area).symlink_to(tree / area, target_is_directory=True)
    return into


def baseline_tree(commit: str, into: Path) -> Path:
    """The repository at `commit`, unpacked (no worktree: nothing is registered with git)."""
    into.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", commit], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into


def run_cli(view: Path, args: list[str], out: Path) -> dict:
    """``cellcal ARGS`` with the package of `view`, in a process of its own: wall s, peak RSS MB, its JSON."""
    env = {**os.environ, "PYTHONPATH": str(view)}
    code = "import sys; from cellcal.cli.main import main; sys.exit(main(sys.argv[1:]))"
    with open(out, "w") as stdout, open(out.with_suffix(".err"), "w") as stderr:
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-c", code, *args], stdout=stdout, stderr=stderr, env=env)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"cellcal {' '.join(args)} ({view}) exited {proc.returncode}: "
                           f"{out.with_suffix('.err').read_text()[-2000:]}")
    return {"wall_s": wall, "peak_mb": usage.ru_maxrss / 1024.0, "doc": json.loads(out.read_text())}


def delta(doc: dict) -> float:
    """DELTA of the module docstring for an identify document: 2 sqrt(2 ftol dof)."""
    per_row = 1 if doc["contact"] else 3
    n_res = per_row * doc["point_rows"] + 3 * doc["position_rows"] + doc["distances"]
    n_free = (sum(p["estimated"] for p in doc["parameters"]) + 3 * len(doc["targets"]) + 3 * doc["points"]
              + (6 if doc["instrument"] else 0))
    return 2.0 * np.sqrt(2.0 * FTOL * max(n_res - n_free, 1))


def identify_agreement(old: dict, new: dict) -> dict:
    """Differences of two identify documents (module docstring); 'ok' when within DELTA."""
    tol = delta(old)
    same = {k: old[k] == new[k] for k in ("unidentifiable", "structural_rank", "noise_rank")}
    same["held_implausible"] = [h["name"] for h in old["held_implausible"]] == [h["name"] for h in new["held_implausible"]]
    same["estimated"] = [p["estimated"] for p in old["parameters"]] == [p["estimated"] for p in new["parameters"]]
    ratios, rel = [], []
    for a, b in zip(old["parameters"], new["parameters"]):
        if a["estimated"] and b["estimated"]:
            ratios.append(abs(a["value"] - b["value"]) / a["std"])
            rel.append(abs(a["std"] - b["std"]) / a["std"])
    for a, b in zip(old["fixture_points"] + list(old["targets"].values()),
                    new["fixture_points"] + list(new["targets"].values())):
        key = "position_mm" if "position_mm" in a else "offset_mm"
        ratios.extend(np.abs(np.subtract(a[key], b[key])) / np.asarray(a["std_mm"]))
        rel.extend(np.abs(np.subtract(a["std_mm"], b["std_mm"])) / np.asarray(a["std_mm"]))
    for key in ("noise_mm", "condition"):
        rel.append(abs(old[key] - new[key]) / abs(old[key]))
    rel.append(abs(old["train"]["mean_mm"] - new["train"]["mean_mm"]) / old["train"]["mean_mm"])
    out = {"tolerance": tol, "max_estimate_diff_in_std": float(max(ratios)), "max_relative_diff": float(max(rel)),
           "same": same}
    out["ok"] = bool(all(same.values()) and out["max_estimate_diff_in_std"] <= tol and out["max_relative_diff"] <= tol)
    return out


def analyze_agreement(old: dict, new: dict, tol: float) -> dict:
    """Differences of two analyze documents (module docstring); 'ok' when within tol (relative)."""
    base_old, base_new = old["baseline"]["heldout_mean_mm"], new["baseline"]["heldout_mean_mm"]
    means_old = np.array([c["heldout_mean_mm"] for c in old["candidates"]])
    means_new = np.array([c["heldout_mean_mm"] for c in new["candidates"]])
    rel = [abs(base_old - base_new) / base_old,
           abs(old["extended"]["heldout_mean_mm"] - new["extended"]["heldout_mean_mm"]) / base_old]
    if len(means_old) == len(means_new):
        rel.extend(np.abs(np.sort(means_old) - np.sort(means_new)) / base_old)
    relabelled, gaining = [], []
    for a, b in zip(old["candidates"], new["candidates"]):
        if a["label"] != b["label"]:
            gains = max(1.0 - a["heldout_mean_mm"] / base_old, 1.0 - b["heldout_mean_mm"] / base_new)
            (gaining if gains > tol else relabelled).append(f"{a['label']} -> {b['label']}")
    same = {"cause": old["cause"] == new["cause"], "where": old["where"] == new["where"],
            "candidates": len(means_old) == len(means_new), "relabelled_with_a_gain": not gaining}
    out = {"tolerance": tol, "max_relative_diff": float(max(rel)), "same": same,
           "relabelled_without_gain": relabelled, "relabelled_with_gain": gaining}
    out["ok"] = bool(all(same.values()) and out["max_relative_diff"] <= tol)
    return out


def one_campaign(label: str, folder: Path, views: dict, kw: dict, timed: bool) -> dict:
    """Generate a campaign, run identify and analyze on it with both codes; timings and agreement."""
    data_csv, fixture, plate = campaign(folder, **kw)
    row = {"label": label, "rows": len(plate.q), **{k: v for k, v in kw.items()}}
    for command in ("identify", "analyze"):
        args = [command, "--robot", "ur10e", "--data", str(data_csv), "--fixture", str(fixture), "--json"]
        runs = {}
        for code in ("old", "new"):
            print(f"{label}: {command}, {code} code ...", file=sys.stderr, flush=True)
            runs[code] = run_cli(views[code], args, folder / f"{command}-{code}.json")
        row[command] = {code: {"wall_s": r["wall_s"], "peak_mb": r["peak_mb"], "seconds": r["doc"]["seconds"]}
                        for code, r in runs.items()}
        if command == "identify":
            row["identify"]["agreement"] = identify_agreement(runs["old"]["doc"], runs["new"]["doc"])
            tol = row["identify"]["agreement"]["tolerance"]
        else:
            row["analyze"]["agreement"] = analyze_agreement(runs["old"]["doc"], runs["new"]["doc"], tol)
            row["analyze"]["cause"] = runs["new"]["doc"]["cause"]
    row["timed"] = timed
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--setups", type=int, default=100, help="placements of the bar in the timed campaign")
    p.add_argument("--per-socket", type=int, default=8, help="seats per socket")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--base", default=BASE, help="the baseline's commit (default: the last before the change)")
    p.add_argument("--no-check", action="store_true", help="the timed campaign only, no check campaigns")
    p.add_argument("--keep", metavar="DIR", help="keep the campaigns and every output in DIR")
    args = p.parse_args(argv)
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="fixture-speed-"))
    views = {"old": package_view(baseline_tree(args.base, work / "base"), work / "view-old"),
             "new": package_view(ROOT, work / "view-new")}
    campaigns = [("sockets", dict(setups=args.setups, per_socket=args.per_socket, seed=args.seed), True)]
    if not args.no_check:
        campaigns += [("sockets, periodic error at joint 5",
                       dict(setups=args.setups, per_socket=args.per_socket, seed=args.seed + 1, amp_deg=0.08,
                            sd_mm=0.05), False),
                      ("stylus balls", dict(setups=max(args.setups // 4, 4), per_socket=12, seed=args.seed + 2,
                                            stylus_radius_mm=4.0), False)]
    rows = [one_campaign(label, work / f"campaign-{i}", views, kw, timed) for i, (label, kw, timed) in
            enumerate(campaigns)]
    timed = rows[0]
    print(f"point-form campaign: UR10e, {args.setups} setups x 2 sockets x {args.per_socket} seats = {timed['rows']} "
          f"rows; the old code is commit {args.base[:10]}; one process per run, BLAS single-threaded")
    print(f"{'command':10s}{'code':>5s}{'wall s':>9s}{'own s':>9s}{'peak MB':>9s}{'ratio':>8s}{'MB ratio':>10s}"
          f"{'target':>9s}")
    met = True
    for command in ("identify", "analyze"):
        old, new = timed[command]["old"], timed[command]["new"]
        ok = new["wall_s"] <= TARGET_S[command] if args.setups == 100 else None
        met &= ok is not False
        for code, r in (("old", old), ("new", new)):
            ratio = f"{r['wall_s'] / old['wall_s']:8.3f}{r['peak_mb'] / old['peak_mb']:10.3f}"
            target = "" if code == "old" or ok is None else (f"{'met' if ok else 'NOT met':>9s}")
            print(f"{command:10s}{code:>5s}{r['wall_s']:9.2f}{r['seconds']:9.2f}{r['peak_mb']:9.0f}{ratio}{target}")
        print(f"{'':10s}{'':>5s}  old / new: {old['wall_s'] / new['wall_s']:.1f}x faster, "
              f"{old['peak_mb'] / new['peak_mb']:.1f}x less memory (target <= {TARGET_S[command]:g} s)")
    agree = True
    print("agreement, old vs new (tolerance DELTA = 2 sqrt(2 ftol dof), module docstring):")
    for r in rows:
        a, b = r["identify"]["agreement"], r["analyze"]["agreement"]
        agree &= a["ok"] and b["ok"]
        print(f"  {r['label']} ({r['rows']} rows): identify {'ok' if a['ok'] else 'DIFFERS'} (estimates within "
              f"{a['max_estimate_diff_in_std']:.2g} std, other numbers {a['max_relative_diff']:.2g} relative; "
              f"DELTA {a['tolerance']:.2g}); analyze {'ok' if b['ok'] else 'DIFFERS'} (cause {r['analyze']['cause']}, "
              f"held-out means within {b['max_relative_diff']:.2g} relative)"
              + (f"; without gain, relabelled: {'; '.join(b['relabelled_without_gain'])}"
                 if b["relabelled_without_gain"] else ""))
        for name, same in {**a["same"], **b["same"]}.items():
            if not same:
                print(f"    differs: {name}")
    out = ROOT / "bench" / "results"
    out.mkdir(parents=True, exist_ok=True)
    env = {"python": platform.python_version(), "numpy": np.__version__, "cpus": os.cpu_count(),
           "load_at_end": os.getloadavg(), "base": args.base}
    path = out / f"fixture-speed-{args.setups}.json"
    path.write_text(json.dumps({"args": vars(args), "environment": env, "campaigns": rows}, indent=1,
                               default=lambda v: v.item()))  # numpy scalars
    print(f"targets {'met' if met else 'NOT met'}; old and new {'agree' if agree else 'DIFFER'}; every number in {path}")
    return 0 if met and agree else 1


if __name__ == "__main__":
    sys.exit(main())
