"""Long URScript programs of every motion form, as an offline programming system writes them, and the
calibrated models to compensate them with (``cellcal compensate --program``'s bench and tests).

The joints a program visits are a random walk from HOME in steps of up to STEP_DEG per joint,
reflected at WINDOW_DEG about HOME: a path through a workpiece that stays clear of the joint
limits, of the elbow's stretched and the wrist's aligned configurations, and of the arm's own
column, however long the program (an unbounded walk leaves the limits after a few thousand
targets). Poses are the nominal forward kinematics of those joints with the tool in force, so
the controller solves each from the previous target's joints on the branch written.
"""
from __future__ import annotations

import numpy as np

from cellcal.sims.physics.physical_arm import HiddenEffect, PhysicalArm
from cellcal.sims.physics.workspace import full_workspace
from cellcal.solvers.compensation.calibrated_model import from_fit
from cellcal.solvers.geometry import se3
from cellcal.solvers.geometry.inverse import tcp_frames

HOME_DEG = np.array([20.0, -100.0, 100.0, -90.0, -90.0, 10.0])
STEP_DEG = 3.0  # the largest move of a joint between two targets: a few cm of path
WINDOW_DEG = np.array([60.0, 20.0, 35.0, 60.0, 40.0, 90.0])  # the walk's reach about HOME, per joint
TOOLS = (  # set_tcp poses (m, rad), in turn: None is the controller's own (--tcp-mm, the calibrated target)
    None, (0.0, 0.0, 0.1, 0.0, 0.0, 0.0), (0.0, 0.0, 0.1, 0.1, -0.2, 0.3), (0.02, -0.01, 0.15, 0.0, 0.0, 1.2))


def walk(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 6) rad: the joints of a program's targets in order (module docstring)."""
    home, window = np.deg2rad(HOME_DEG), np.deg2rad(WINDOW_DEG)
    steps = np.deg2rad(rng.uniform(-STEP_DEG, STEP_DEG, (n, 6)))
    steps[0] = 0.0
    x = np.cumsum(steps, axis=0)  # reflected into [-window, window]: a triangle wave of the free walk
    period = 4.0 * window
    x = np.abs((x + window) % period - 2.0 * window) - window
    return home + x


def literal(values, pose: bool) -> str:
    return ("p[" if pose else "[") + ", ".join(f"{v:.6f}" for v in values) + "]"


def long_program(model, tool_mm, lines: int = 50_000, seed: int = 3) -> str:
    """A program of about `lines` lines (at least one block) in blocks, each the path of one station: a
    set_tcp (the tools of TOOLS in turn, the controller's own written out after the first block; every
    20th block a tool computed at run time, so its targets cannot be compensated), a movej to joints, then
    a path of 5 to 80 targets: movel to poses mostly, movep and movec through two poses, every 16th a movej
    to joints, every 10th a movel computed at run time, a comment every 25th line; a sleep last. `tool_mm`
    (3,) is the controller's own tool point (the first block's)."""
    rng = np.random.default_rng(seed)
    own = np.r_[np.asarray(tool_mm, float) / 1000.0, 0, 0, 0]
    plan = []  # per block: its tool (None: the controller's own, "runtime") and its lines' kinds
    count = 2
    while count < lines - 2 or not plan:
        b = len(plan)
        tool = "runtime" if b % 20 == 19 else TOOLS[b % len(TOOLS)]
        kinds = ["joints"]
        for k in range(int(rng.integers(5, 81))):
            kinds.append("runtime" if k % 10 == 9 else "joints" if k % 16 == 15 else
                         "movec" if k % 7 == 3 else "movep" if k % 5 == 2 else "movel")
            if k % 25 == 24:
                kinds.append("comment")
        plan.append((tool, kinds + ["sleep"]))
        count += len(kinds) + 2
    n = sum(2 if k == "movec" else k in ("joints", "movel", "movep") for _, kinds in plan for k in kinds)
    q = walk(n, rng)
    tools = [own if tool is None or tool == "runtime" else np.array(tool) for tool, kinds in plan
             for k in kinds for _ in range(2 if k == "movec" else k in ("joints", "movel", "movep"))]
    poses = np.zeros((n, 6))
    for tool in {tuple(t) for t in tools}:
        rows = np.flatnonzero([tuple(t) == tool for t in tools])
        rot, p = tcp_frames(model, q[rows], np.array(tool))
        poses[rows] = np.column_stack([p, se3.matrix_to_rotvec(rot)])
    out = ["# a long path, poses from an offline system (nominal kinematics)", "def long_path():"]
    i = 0
    for b, (tool, kinds) in enumerate(plan):
        if tool == "runtime":
            out.append("  set_tcp(tool_of(station))  # chosen at run time")
        elif tool is None:
            out.append("  # the controller's own tool" if b == 0 else
                       f"  set_tcp({literal(own, True)})  # the controller's own tool")
        else:
            out.append(f"  set_tcp({literal(tool, True)})")
        for k in kinds:
            if k == "joints":
                out.append(f"  movej({literal(q[i], False)}, a=1.4, v=1.05)")
            elif k == "movel":
                out.append(f"  movel({literal(poses[i], True)}, a=1.2, v=0.25, r=0.002)")
            elif k == "movep":
                out.append(f"  movep(pose={literal(poses[i], True)}, a=1.2, v=0.25, r=0.002)")
            elif k == "movec":
                out.append(f"  movec({literal(poses[i], True)}, {literal(poses[i + 1], True)}, a=1.2, v=0.1, "
                           "r=0, mode=1)")
                i += 1
            elif k == "runtime":
                out.append("  movel(pose_trans(get_actual_tcp_pose(), p[0, 0, 0.001, 0, 0, 0]), a=1.2, v=0.25)")
                continue
            elif k == "comment":
                out.append(f"  # station {b + 1}, line {len(out) + 1}")
                continue
            else:
                out.append(f"  sleep(0.01)  # station {b + 1} done")
                continue
            i += 1
    return "\n".join(out + ["end", "long_path()", ""])


def calibrated_with_compliance(model, seed: int = 5, poses: int = 250, tool_mm=(0.0, 0.0, 100.0)):
    """(the calibrated model, the simulated arm): hidden geometric errors and a hidden joint-2 compliance,
    ``analyze`` on `poses` simulated tracker positions (as bench/compensate_bench.py calibrates)."""
    from cellcal.solvers.analysis.analyze import AnalyzeOptions, analyze

    rng = np.random.default_rng(seed)
    arm = PhysicalArm(model, rng, [HiddenEffect("joint_compliance", 1, rms_mm=0.5)],
                      target_offsets=[np.asarray(tool_mm, float)])
    data = arm.campaign(full_workspace(model, poses, rng))
    s = analyze(model, data.obs, data.ctx, AnalyzeOptions(causes=("joint_compliance",))).extended
    return from_fit(model, data.obs.target_names, s.x, s.terms, s.theta), arm
