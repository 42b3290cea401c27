"""How long ``cellcal --help`` takes to answer, against importing numpy and scipy.optimize.

Every case is a fresh interpreter (as a person typing the command gets), timed from
start to exit, median of REPEATS:

* ``numpy + scipy.optimize``: the baseline, the import every computing command pays.
* ``cellcal --help``: the command table, which imports no sub-command.
* ``--help, every command loaded``: the same help with every sub-command's module
  imported first, as the command line did before it loaded a sub-command only when it
  runs (matplotlib, pymodbus and the solvers included).
* ``cellcal --version``.

Goal: ``cellcal --help`` in at most 0.6x the baseline.

    python -m bench.cli_startup_bench
"""
from __future__ import annotations

import statistics
import subprocess
import sys
import time

REPEATS = 9
CASES = {
    "numpy + scipy.optimize (baseline)": "import numpy, scipy.optimize",
    "cellcal --help": "import sys; sys.argv = ['cellcal', '--help']\n"
                      "from cellcal.cli.main import main\ntry:\n    main()\nexcept SystemExit:\n    pass",
    "--help, every command loaded": "from cellcal.cli.main import build_parser\n"
                                    "try:\n    build_parser(every=True).parse_args(['--help'])\nexcept SystemExit:\n    pass",
    "cellcal --version": "from cellcal.cli.main import main\ntry:\n    main(['--version'])\nexcept SystemExit:\n    pass",
}


def seconds(code: str) -> float:
    times = []
    for _ in range(REPEATS):
        start = time.perf_counter()
        subprocess.run([sys.executable, "-c", code], check=True, stdout=subprocess.DEVNULL)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    for code in CASES.values():  # warm the file cache once
        subprocess.run([sys.executable, "-c", code], check=True, stdout=subprocess.DEVNULL)
    result = {name: seconds(code) for name, code in CASES.items()}
    base = result["numpy + scipy.optimize (baseline)"]
    print(f"{'case':<36} {'median s':>9} {'x baseline':>11}")
    for name, s in result.items():
        print(f"{name:<36} {s:9.3f} {s / base:11.2f}")
    ratio = result["cellcal --help"] / base
    print(f"\ncellcal --help: {ratio:.2f} x the baseline (goal <= 0.6); "
          f"{result['--help, every command loaded'] / result['cellcal --help']:.1f} x faster than loading every command")


if __name__ == "__main__":
    main()
