"""Run pybotics' calibration on cellcal data, in a bench-only virtual environment.

pybotics 3.x pins numpy<2, so it never enters the product's environment: on first
use this module creates ``bench/.venv-pybotics`` with the running interpreter's
``venv`` module and installs pybotics from PyPI with pip. The data goes to
``pybotics_baseline.py`` (run with the venv's interpreter) as an .npz file and
the result comes back as JSON.

Convention mapping. pybotics chains are modified DH (Craig): each link is
Rx(alpha) Tx(a) Rz(theta + q) Tz(d). A classic-DH chain (ours for the IRB4600:
Rz(theta + q) Tz(d) Tx(a) Rx(alpha) per joint) regroups exactly:

    prod_j [Rz Tz Tx Rx]_j = [Rz Tz]_1 [Tx Rx Rz Tz]_2 ... [Tx Rx Rz Tz]_n [Tx Rx]_n

so MDH link j gets (alpha_{j-1}, a_{j-1}, theta_j, d_j) with alpha_0 = a_0 = 0, and
the trailing Tx(a_n) Rx(alpha_n) moves into the tool. This holds for every value of
the parameters, not just the nominal ones, so both tools search the same model
family. The tool is that trailing transform followed by the target offset; only
its position is optimised (positions alone cannot see the tool's orientation).
The world frame is cellcal's instrument -> base transform, all six entries free
(pybotics stores it as xyz + Euler ZYX, singular at a pitch of +-90 deg).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from cellcal.solvers.geometry import se3
from cellcal.solvers.identification.measurement_model import Layout, Observations, predict

HERE = Path(__file__).resolve().parent
VENV = HERE / ".venv-pybotics"
SCRIPT = HERE / "pybotics_baseline.py"
REQUIREMENT = "pybotics==3.1.2"  # latest 3.x; its metadata pins numpy>=1.22,<2.0


class PyboticsUnavailable(RuntimeError):
    """pybotics could not be installed or run; the message says exactly what failed."""


def venv_python() -> Path:
    return VENV / ("Scripts/python.exe" if os.name == "nt" else "bin/python")


def _run(cmd: list[str], what: str, timeout: float) -> subprocess.CompletedProcess:
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        raise PyboticsUnavailable(f"{what}: no answer within {timeout:.0f} s: {' '.join(cmd)}") from None
    if proc.returncode != 0:
        tail = "\n".join((proc.stderr or proc.stdout).strip().splitlines()[-15:])
        raise PyboticsUnavailable(f"{what} failed (exit {proc.returncode}): {' '.join(cmd)}\n{tail}")
    return proc


def ensure_venv(say=lambda msg: None, timeout: float = 900.0) -> Path:
    """The venv's interpreter, creating the venv and installing pybotics if needed."""
    py = venv_python()
    probe = [str(py), "-c", "import pybotics.optimization"]
    if py.exists() and subprocess.run(probe, capture_output=True).returncode == 0:
        return py
    say(f"creating {VENV} and installing {REQUIREMENT} (first use only)")
    _run([sys.executable, "-m", "venv", "--clear", str(VENV)], "creating the pybotics venv", timeout)
    _run([str(py), "-m", "pip", "install", "--disable-pip-version-check", "-q", REQUIREMENT],
         f"pip install {REQUIREMENT}", timeout)
    _run(probe, "importing pybotics in its venv", timeout)
    return py


def _tx_rx(a: float, alpha: float) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = se3.rot("x", alpha)
    t[0, 3] = a
    return t


def to_pybotics(layout: Layout, x: np.ndarray, kin_free: np.ndarray) -> dict[str, np.ndarray]:
    """pybotics' robot (MDH rows, tool, world) and masks for cellcal's unknown vector x.

    kin_free marks the kinematic parameters to optimise; a classic-DH a_n, alpha_n
    has no MDH counterpart and is absorbed by the free tool position.
    """
    model = layout.model
    if len(model.chains) != 1 or len(layout.target_names) != 1:
        raise ValueError("pybotics handles one serial chain with one tool")
    chain = model.chains[model.default_chain]
    if any(len(el.joints) > 1 for el in chain.elements) or not np.allclose(chain.end, np.eye(4)):
        raise ValueError(f"{model.name}: coupled joints or a fixed end transform have no pybotics form")
    if any(name.startswith("beta") for name in model.param_names):
        raise ValueError(f"{model.name}: Hayati beta parameters have no pybotics form")
    n, k = model.n_joints, x[: layout.n_kin]
    mdh = np.zeros((n, 4))  # columns: alpha, a, theta, d
    mask = np.zeros((n, 4), bool)

    def put(row, col, name):
        i = model.index(name)
        mdh[row, col], mask[row, col] = k[i], kin_free[i]

    tail = np.eye(4)
    for j in range(1, n + 1):
        put(j - 1, 2, f"theta{j}")
        put(j - 1, 3, f"d{j}")
        if model.convention == "mdh":
            put(j - 1, 0, f"alpha{j}")
            put(j - 1, 1, f"a{j}")
        elif j < n:
            put(j, 0, f"alpha{j}")
            put(j, 1, f"a{j}")
        else:
            tail = _tx_rx(k[model.index(f"a{j}")], k[model.index(f"alpha{j}")])
    tool = tail.copy()
    tool[:3, 3] = tail[:3, :3] @ x[layout.target(0)] + tail[:3, 3]
    base = x[layout.base]
    world = se3.homogeneous(se3.rotvec_to_matrix(base[3:]), base[:3])
    return {"mdh": mdh, "kc_mask": mask.ravel(), "tool": tool,
            "tool_mask": np.array([True] * 3 + [False] * 3), "world": world,
            "world_mask": np.ones(6, bool)}


def run_pybotics(layout: Layout, cal: Observations, val: Observations, x_start: np.ndarray,
                 kin_free: np.ndarray, variants=("default", "lm"), say=lambda msg: None,
                 timeout: float = 3600.0) -> dict:
    """Calibrate with pybotics from x_start; its JSON result plus the wall-clock time.

    Each variant's ``seconds`` is pybotics' own optimisation time, measured inside the
    subprocess; ``wall_seconds`` (all variants) adds interpreter start, imports and
    the file exchange.
    """
    py = ensure_venv(say)
    arrays = to_pybotics(layout, x_start, kin_free)
    with tempfile.TemporaryDirectory(prefix="cellcal-pybotics-") as tmp:
        data, out = Path(tmp) / "data.npz", Path(tmp) / "result.json"
        np.savez(data, q_cal=cal.q, xyz_cal=cal.xyz_mm, q_val=val.q, xyz_val=val.xyz_mm,
                 check_xyz=predict(layout, x_start, cal), **arrays)
        say(f"pybotics: calibrating {int(arrays['kc_mask'].sum())} MDH parameters, tool position "
            f"and world frame on {len(cal)} poses")
        t0 = time.perf_counter()
        _run([str(py), str(SCRIPT), str(data), str(out), "--variants", ",".join(variants)],
             "pybotics calibration", timeout)
        wall = time.perf_counter() - t0
        result = json.loads(out.read_text(encoding="utf-8"))
    result["wall_seconds"] = wall
    return result


def main(argv: list[str] | None = None) -> int:
    """``python -m bench.pybotics_runner``: create the venv now and print its versions."""
    import argparse

    argparse.ArgumentParser(description=main.__doc__).parse_args(argv)
    try:
        py = ensure_venv(lambda msg: print(msg, file=sys.stderr))
    except PyboticsUnavailable as exc:
        print(exc, file=sys.stderr)
        return 1
    subprocess.run([str(py), "-m", "pip", "list", "--disable-pip-version-check"], check=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
