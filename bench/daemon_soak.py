"""Soak: the daemon through N complete button-started runs on the networked simulated cell.

The suite's leak test (tests/e2e/test_daemon_e2e.py) makes 100 runs of which most are refused
or aborted, to stay within the suite's time; this runs N *complete* runs of the same short
tcp-laser (each to its verdict) through ``cellcal daemon`` and the Modbus panel, and counts
what the daemon process holds (file descriptors, sockets, threads, child processes) after
a first warm-up run and after the last. Real time: about 7 s a run.

    python -m bench.daemon_soak --runs 100
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from support.daemon_harness import Daemon, Net, one_run, resources, settled  # noqa: E402  (the suite's harness)

from cellcal.daemon.store import Store  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=100, help="complete runs after the warm-up (default 100)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as folder:
        net = Net(Path(folder))
        try:
            net.reset()
            daemon = Daemon(net, Path(folder))
            try:
                one_run(net, "complete")  # what a first run opens for good
                before = settled(daemon.proc.pid, resources(daemon.proc.pid))
                t0 = time.monotonic()
                for k in range(args.runs):
                    one_run(net, "complete")
                    if (k + 1) % 10 == 0:
                        print(f"{k + 1}/{args.runs} runs, {time.monotonic() - t0:.0f} s, "
                              f"daemon holds {resources(daemon.proc.pid)}", file=sys.stderr, flush=True)
                took_s = time.monotonic() - t0
                after = settled(daemon.proc.pid, before)
                store = Store.open(daemon.state_dir)
                runs = store.runs(args.runs)
                store.close()
            finally:
                code = daemon.stop()
        finally:
            net.close()
    endings = Counter(f"{r.state}/{r.result_code}" for r in runs)
    report = {"runs": args.runs, "took_s": round(took_s, 1), "per_run_s": round(took_s / args.runs, 2),
              "before": before, "after": after, "leaked": {k: after[k] - before[k] for k in before},
              "endings": dict(endings), "daemon_exit": code}
    print(json.dumps(report, indent=1))
    return 0 if after == before and code == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
