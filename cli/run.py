"""``cellcal run ROUTINE --cell CELL.yaml [--tool ID] [--dry-run] [--json] [--from DATASET]``.

Plans the routine from the cell file, checks every motion against the cell's limits
(``--dry-run`` stops there), moves and records, writes the dataset, solves and gates.
``--from DATASET`` re-solves a recorded dataset offline with the same code;
``--resume DATASET`` continues a campaign a fault stopped (routines that can). On a
simulated cell the result also carries ``sim_truth``: the error against the hidden truth.
``--tool ID`` runs with that tool of the cell's tool table mounted (its drawing, bands and
routine sections; on an in-process simulated cell, its real frame); the JSON says ``tool_id``.

Nothing is written to the controller here (the daemon writes results back): the JSON says
``passed_gates`` (every quality gate passed, so the result may be written back) and
``written_back: false``.

Exit status: 0 the result passed every gate; 1 a device fault,
a computation that failed, or a result that failed a gate (the JSON still comes, with
``passed_gates: false`` and the reasons); 2 bad usage, a bad cell file, a plan that would
leave the cell's limits or that the cell cannot carry out (a pose out of reach, a device
the routine needs), an ``--out`` folder that cannot be written (checked before anything
moves), or a dataset that cannot be used. ``--from`` also says when the store recorded the
dataset with another checksum (``--state-dir``; a store is never created for it).

A routine that waits for the operator (``kinematic-fixture`` with ``move_by: operator``: the plate
moved between placements) asks on the terminal and waits for Enter, up to its
``confirm_timeout_s`` (then exit 1, nothing written); with a standard input that is no terminal it
is refused before anything moves (exit 2): run it through the daemon and the panel's confirm
button, or with fixed placements.
"""
from __future__ import annotations

import json
import os
import select
import sys

import numpy as np

from cellcal.config.cells import TOOL_IDS
from cellcal.config.robot_files import load_robot
from cellcal.drivers import registry as drivers_registry
from cellcal.drivers.interfaces import Operator, OperatorTimeout
from cellcal.routines.framework import registry, runner
from cellcal.routines.framework.base import (CalibrateFirst, NotForThisCell, PlanRefused, Result, RoutineError,
                                             frame_text, gate_line, jsonable)
from cellcal.routines.framework.records import read_dataset
from cellcal.solvers.geometry import se3
from cellcal.solvers.geometry.inverse import tcp_frames
from cellcal.solvers.identification.measurement_model import Layout, Observations, predict
from cellcal.daemon.cells import NoToolMounted, load_cell, mounted_tool, open_drivers
from cellcal.daemon.claims import held
from cellcal.daemon.store import Store, StoreError, file_sha256, state_dir as store_folder
from cellcal.cli.common import STATE_HELP, UsageError, counted, print_progress, whole, writable_folder


def _score(result: Result, cell) -> None:
    truth = drivers_registry.simulated_truth(cell, load_robot(cell.robot))
    if truth is None:
        return
    score = truth.report()
    if result.tool_frame is not None:
        score.update(truth.score_tool_frame(result.tool_frame))  # the frame as written: kept parts too
        score["determined"] = sorted(result.determines)  # the errors of the rest are the kept frame's
    if result.routine == "tracker" and result.dataset and truth.tool is not None:
        score.update(_score_kinematics(result, truth, load_robot(cell.robot)))
    if result.routine == "kinematic-fixture" and "kinematics" in result.extra and truth.tool is not None:
        score.update(_score_fixture(result, truth, load_robot(cell.robot), cell))
    if result.routine == "handshake" and result.frame is not None:
        score.update(truth.score_base_frame(result.frame["pose_m_rad"]))
        score.update(truth.score_tips(*(np.asarray(result.extra[f"tip_{n}_mm"]) / 1e3 for n in "ab")))
    result.sim_truth = score


def _score_kinematics(result: Result, truth, model) -> dict:
    """A kinematic calibration against the arm as built and the real tool tip (where the
    simulated tracker's target sits, measured in the robot base frame), on the validation
    rows of its dataset: the mean error the identified model and the true one leave on the
    measured positions, and the identified model's distance from the true positions."""
    data = read_dataset(result.dataset, result.routine, ("split", "target"))
    val = np.asarray(data["split"]) == "val"
    if not val.any():
        return {}
    layout = Layout(model, tuple(dict.fromkeys(np.asarray(data["target"])[~val]))[:1])
    value = {p.name: p.value for p in result.parameters}
    found = np.array([np.deg2rad(value[n]) if a else value[n] for n, a in zip(layout.names, layout.is_angle)])
    true = layout.initial(base=np.zeros(6), offsets=[truth.tool.tcp_m * 1e3])
    true[: layout.n_kin] = truth.arm_params
    q = data.stack(*[f"q{j}_rad" for j in range(1, model.n_joints + 1)])[val]
    obs = Observations(q, data.stack("x_mm", "y_mm", "z_mm")[val], np.zeros(len(q), int), layout.target_names)
    p_found, p_true = predict(layout, found, obs), predict(layout, true, obs)
    after, floor = (float(np.linalg.norm(p - obs.xyz_mm, axis=1).mean()) for p in (p_found, p_true))
    error = np.linalg.norm(p_found - p_true, axis=1)
    return {"validation_mean_mm": after, "floor_mean_mm": floor, "validation_over_floor": after / floor,
            "model_error_mean_mm": float(error.mean()), "model_error_max_mm": float(error.max())}


WORKSPACE_POSES = 300  # random poses over the workspace a fixture calibration is scored at
WORKSPACE_SEED = 0


def _score_fixture(result: Result, truth, model, cell) -> dict:
    """A calibration from fixtures against the arm as built, over the whole workspace, not only at the
    sockets: at random joint configurations whose real tool tip is inside the workspace box, the mean
    distance between the tip the calibrated model predicts (its kinematics and its fitted tip offset)
    and the real tip, after the one rigid motion that best lays the one on the other (fixture data fix
    no base frame: the points live in a frame of the plate's, so the error is relative to the plate);
    next to it the nominal arm's, with the real tip (what a perfect tool calibration on the drawn arm
    would give)."""
    rng = np.random.default_rng(WORKSPACE_SEED)
    lo, hi = np.asarray(cell.workspace_min_m) * 1e3, np.asarray(cell.workspace_max_m) * 1e3
    tip_true = truth.tool.tcp_m * 1e3 - truth.tool.axis * truth.tool.radius_m * 1e3  # the rounding's centre
    q = rng.uniform(-np.pi, np.pi, (20 * WORKSPACE_POSES, model.n_joints))
    real = tcp_frames(model, q, np.r_[tip_true / 1e3, 0, 0, 0], params=truth.arm_params)[1] * 1e3
    inside = np.all((real >= lo) & (real <= hi), axis=1)
    q, real = q[inside][:WORKSPACE_POSES], real[inside][:WORKSPACE_POSES]
    found_tip = np.asarray(result.extra["target_offset_mm"]) / 1e3
    found = tcp_frames(model, q, np.r_[found_tip, 0, 0, 0], params=np.asarray(result.extra["kinematics"]))[1] * 1e3
    nominal = tcp_frames(model, q, np.r_[tip_true / 1e3, 0, 0, 0])[1] * 1e3

    def mean_error(predicted):
        rotation, shift = se3.rigid_fit(predicted, real)
        return float(np.linalg.norm(predicted @ rotation.T + shift - real, axis=1).mean())

    return {"workspace_poses": int(len(q)), "workspace_mean_mm": mean_error(found),
            "workspace_nominal_mean_mm": mean_error(nominal)}


def _text(result: Result) -> str:
    lines = [f"{result.routine}: " + ("PASSED every gate: may be written back" if result.passed_gates else
                                      "NOT to be written back")]
    if result.verdict is not None:  # a check (tcp-check): its verdict, and the first note says why
        lines.append(f"  verdict {result.verdict.upper()}: {result.notes[0] if result.notes else ''}")
    if result.tool_frame is not None:
        lines.append(f"  tool frame  {frame_text(result.tool_frame)}")
    for p in result.parameters:
        std = "" if p.std is None else f" +- {p.std:.4f}"
        lines.append(f"  {p.name:<28} {p.value:12.4f}{std} {p.unit}")
    lines.append(f"  residual RMS {result.residual_rms_mm:.4f} mm over {len(result.residuals_mm)} measurements "
                 f"(expected noise {result.expected_noise_mm:.4f} mm); condition {result.condition:.3g}")
    if result.cycle_time_s is not None:
        lines.append(f"  cycle time {result.cycle_time_s:.1f} s")
    for g in result.gates:
        lines.append(f"  {gate_line(g)}")
    lines += [f"  note: {n}" for n in result.notes]
    if result.sim_truth:
        t = result.sim_truth
        if "position_error_mm" in t:
            determined = t.get("determined", ("tip", "axis"))
            kept = {k: "" if k in determined else " (kept, not determined by this run)" for k in ("tip", "axis")}
            lines.append(f"  against the simulation's hidden truth: TCP {t['position_error_mm']:.4f} mm{kept['tip']}, "
                         f"axis {t['axis_error_deg']:.4f} deg{kept['axis']}")
        if "base_position_error_mm" in t:
            lines.append(f"  against the simulation's hidden truth: robot b's base {t['base_position_error_mm']:.4f} mm, "
                         f"{t['base_rotation_error_deg']:.5f} deg; tips {t.get('tip_a_error_mm', float('nan')):.4f} "
                         f"and {t.get('tip_b_error_mm', float('nan')):.4f} mm")
    if result.dataset:
        lines.append(f"  dataset: {result.dataset}")
    return "\n".join(lines)


RUNS_SEARCHED = 100_000  # the latest runs whose datasets --from is looked up among (years of a cell's runs)


def _say_if_edited(path, state_dir: str | None) -> None:
    """A dataset the store recorded (found by its path in the --state-dir / $STATE_DIRECTORY store,
    when one exists) that no longer has the checksum recorded with it: say so on stderr. The
    re-solve goes on; it is of the data as they are now."""
    try:
        store = Store.open(store_folder(state_dir), create=False)
    except StoreError:
        return  # no store here (or not readable): nothing recorded to compare with
    try:
        wanted = os.path.realpath(path)
        run = next((r for r in store.runs(RUNS_SEARCHED) if r.dataset_path and r.dataset_sha256
                    and os.path.realpath(r.dataset_path) == wanted), None)
    finally:
        store.close()
    try:
        if run is not None and file_sha256(path) != run.dataset_sha256:
            print_progress(f"warning: {path}: changed since run {run.id} recorded it (sha256 "
                           f"{run.dataset_sha256[:12]}... then, {file_sha256(path)[:12]}... now); this re-solves "
                           "the data as they are now")
    except OSError:
        pass  # unreadable: reading the dataset says why


def cmd_run(args) -> int:
    try:
        cell = load_cell(args.cell)
        if args.tool is not None:  # another tool of the table mounted: its sections read as the file's are
            cell = cell.with_tool(args.tool)
            registry.check_sections(cell)
        if args.routine not in registry.available():
            raise UsageError(f"no routine named {args.routine!r} (routines: {', '.join(registry.available())})")
        if args.from_dataset and args.resume:
            raise UsageError("--from re-solves a dataset, --resume measures the rest of one: give one of them")
        if args.from_dataset:
            _say_if_edited(args.from_dataset, args.state_dir)
            result = runner.solve_file(args.routine, cell, args.from_dataset)
        else:
            prepared = runner.prepare(args.routine, cell, resume=args.resume)
            if args.dry_run:
                summary = {"routine": args.routine, "cell": cell.path, "tool_id": _tool_id(cell),
                           "moves": len(prepared.plan),
                           "within_limits": True,
                           "plan": [{"kind": m.kind, "label": m.label} for m in prepared.plan]}
                if args.json:
                    print(json.dumps(summary))
                else:
                    print(f"{args.routine}: {counted(len(prepared.plan), 'move')} planned; every one is within the "
                          f"limits of {cell.path} (nothing moved)")
                return 0
            operator = _terminal_operator(args.routine, prepared.routine)
            writable_folder(args.out, "--out")  # the datasets' place, made once the plan stands: nothing moved yet
            # the robot's claim first: while the service (or another run) holds the robot, say so; nothing moves
            with held(cell, kinds=("robot",)), open_drivers(cell) as drivers:
                if cell.mounted_source.kind != "file":  # the panel or the tool changer says which tool is on
                    cell, prepared = _mounted(args, cell, drivers, prepared)
                dataset = runner.measure(prepared, drivers, args.out, print_progress, operator=operator)
            result = runner.solve_run(prepared.context, dataset)  # the run's context: its section read once
    except PlanRefused as exc:
        raise UsageError(f"{args.cell}: plan refused, nothing moved: {exc}") from None
    except NotForThisCell as exc:  # the cell lacks what the routine needs: input at fault, as a refused plan
        raise UsageError(f"{exc}; nothing moved") from None
    except CalibrateFirst as exc:  # a check with nothing to judge against yet
        raise UsageError(f"{args.cell}: {exc}; nothing moved") from None
    _score(result, cell)
    if args.json:
        print(json.dumps({**result.as_json(), "tool_id": _tool_id(cell), "written_back": False}, default=jsonable))
    else:
        if len(cell.tools) > 1:
            print(f"tool {cell.tool.id} ({cell.tool.name}) mounted")
        print(_text(result))
        if result.tool_frame is not None:
            print("  nothing written to the controller (cellcal run never writes; the daemon writes back)")
    return 0 if result.passed_gates and result.verdict != "alarm" else 1  # a check's alarm is a cell failure


class TerminalOperator(Operator):
    """The operator at ``cellcal run``'s terminal: asked on standard error, confirms with Enter.
    What was typed before the question is dropped (a confirm given when none was asked for)."""

    name = "operator at the terminal"

    def __init__(self, stream=None):
        self.stream = sys.stdin if stream is None else stream

    def confirm(self, message: str, *, step: int, timeout_s: float) -> None:
        if self.stream.isatty():
            import termios
            termios.tcflush(self.stream.fileno(), termios.TCIFLUSH)
        print(f"cellcal: {message}; press Enter when done (the run stops after {timeout_s:g} s)",
              file=sys.stderr, flush=True)
        ready, _, _ = select.select([self.stream], [], [], timeout_s)
        if not ready:
            raise OperatorTimeout(self.name, f"no Enter within {timeout_s:g} s (confirm_timeout_s) after asking: "
                                             f"{message}")
        if not self.stream.readline():
            raise RoutineError(f"the terminal's input ended while waiting for the operator ({message})")


def _terminal_operator(name: str, routine) -> Operator | None:
    """The operator to ask for a routine that waits for one (refused up front, UsageError, when
    standard input is no terminal to ask on); None for every other routine."""
    if not routine.asks_operator():
        return None
    if not sys.stdin.isatty():
        selector = registry.routine_class(name).selector
        raise UsageError(f"{routine.cell.path} [{type(routine).section}]: move_by: operator: {name} waits for the "
                         "operator to move the plate between placements and confirm, and standard input is not a "
                         "terminal to ask on; run it through the daemon (`cellcal daemon`, routine selector "
                         f"{selector}, the panel's confirm button), from a terminal, or with the plates fixed at "
                         "their placements (move_by: fixed); nothing moved")
    return TerminalOperator()


def _mounted(args, cell, drivers, prepared):
    """(cell, prepared) for the tool the cell's source says is mounted (``mounted: panel`` or
    the tool changer's inputs): read before anything moves; ``--tool`` must agree with it."""
    try:
        tool_id = mounted_tool(cell, drivers)
    except NoToolMounted as exc:
        raise RoutineError(f"{exc}; nothing moved") from None
    if args.tool is not None and tool_id != args.tool:
        raise UsageError(f"--tool {args.tool}, and {cell.mounted_source.describe()} says tool {tool_id} is "
                         "mounted; nothing moved")
    if tool_id == cell.tool.id:
        return cell, prepared
    cell = cell.with_tool(tool_id)
    registry.check_sections(cell)
    return cell, runner.prepare(args.routine, cell, resume=args.resume)


def _tool_id(cell) -> int | None:
    """The mounted tool's id in the cell's tool table (None: a cell without a tool)."""
    return cell.tool.id if cell.tool is not None else None


def add_parser(sub) -> None:
    p = sub.add_parser("run", help="run a calibration routine on a cell",
                       description="Plan the routine from the cell file, check every motion against the "
                                   "cell's limits, move and record, write the dataset, solve, and check the "
                                   "result's quality gates. Nothing is written to the controller here.")
    p.add_argument("routine", metavar="ROUTINE", help="one of: " + ", ".join(registry.available()))
    p.add_argument("--cell", default="sim", metavar="CELL.yaml",
                   help="cell file, or the name of a shipped cell (default: sim, the simulated cell)")
    p.add_argument("--tool", type=whole(*TOOL_IDS), metavar="ID",
                   help="the tool of the cell's tool table that is mounted (default: the file's `mounted`; "
                        "where the panel or the tool changer says which, it must agree)")
    p.add_argument("--dry-run", action="store_true", help="plan and check every motion; move nothing")
    p.add_argument("--from", dest="from_dataset", metavar="DATASET",
                   help="re-solve a recorded dataset instead of measuring")
    p.add_argument("--resume", metavar="DATASET",
                   help="continue the incomplete dataset a fault left: measure only what it lacks")
    p.add_argument("--out", default="out/runs", metavar="DIR", help="where datasets are written (default: out/runs)")
    p.add_argument("--state-dir", metavar="DIR",
                   help="with --from: the store whose record of the dataset's checksum is compared (never "
                        "created); " + STATE_HELP.removeprefix("the store's folder "))
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=cmd_run)
