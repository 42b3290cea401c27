"""URScript in, URScript out: the scanner finds every motion target and the tool in force, the rewrite
touches only the targets' numbers, and a compensated program driven on the hidden true robot (as its
controller would drive it) lands where the program meant.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from cellcal.cli.main import main
from cellcal.config.model_files import write_calibrated
from cellcal.config.robot_files import load_robot
from cellcal.programs import apply
from cellcal.programs.apply import compensate_program
from cellcal.programs.urscript import (DECIMALS, JOINTS, POSE, RUNTIME, ProgramError, encode, format_number, parse,
                                       read_program, rewrite)
from cellcal.sims.physics.physical_arm import PhysicalArm
from cellcal.sims.physics.workspace import full_workspace
from cellcal.solvers.compensation import compensate as solver
from cellcal.solvers.geometry import se3
from cellcal.solvers.compensation.calibrated_model import from_fit
from cellcal.solvers.identification.identify import IdentifyOptions, identify
from cellcal.solvers.geometry.inverse import inverse, tcp_frames
from cellcal.solvers.analysis.effects import Context, approach_directions

from support.programs import long_program

# -- the scanner ---------------------------------------------------------------------------------------------

EVERY_FORM = """\
# A program of every motion form. movel(p[9, 9, 9, 9, 9, 9]) in a comment is no call.
def prog():
  textmsg("movej([9, 9, 9, 9, 9, 9]) in a string is no call either")
  textmsg('nor movec(p[9,9,9,9,9,9], p[9,9,9,9,9,9]) in single quotes \\' with an escaped quote')
  movej([0.1, -1.5, 1.4, -1.2, -1.57, 0], a=1.4, v=1.05)
  movel(p[.5, -.2, .4, 0, 3.14, 0], a=1.2, v=0.25, r=0.01)
  set_tcp(p[0, 0, 0.1, 0, 0, 0])
  movel([0.2, -1.4, 1.3, -1.3, -1.57, 0], a=1.2, v=0.25, t=0, r=0)
  movej(p[0.45, -0.25, 0.35, 0.0, 3.1, 0.1], v=1.05)
  movep(p[0.4, -0.3, 0.35, -0.01, 3.1, 0.1], a=1.2, v=0.25, r=0.002)
  movec(p[0.41, -0.31, 0.35, 0, 3.1, 0], p[0.42, -0.3, 0.36, 0, 3.1, 0], a=1.2, v=0.1, r=0, mode=1)
  movel(pose=p[0.5, -0.2, 0.4, 0, 3.14, 0], v=0.25)
  movec(p[0.41, -0.31, 0.35, 0, 3.1, 0], pose_to=p[0.42, -0.3, 0.36, 0, 3.1, 0], mode=0)
  movej(
    [0.3, -1.3,   # a joint list over two lines
     1.2, -1.4, -1.57, 0.5],
    a=1.4, v=1.05)
  movel(p[0.5, -0.2, \\
          0.41, 0, 3.14, 0])
  my_movel(p[9, 9, 9, 9, 9, 9])
end
def movel_twice(pose_a):
  movel(pose_a)
end
"""


def test_every_motion_form_is_found_with_its_values_and_place():
    program = parse(EVERY_FORM, "prog.script")
    found = [(t.line, t.call, t.role, t.kind) for t in program.targets]
    assert found == [
        (5, "movej", "q", JOINTS), (6, "movel", "pose", POSE), (8, "movel", "pose", JOINTS),
        (9, "movej", "q", POSE), (10, "movep", "pose", POSE),
        (11, "movec", "pose_via", POSE), (11, "movec", "pose_to", POSE),
        (12, "movel", "pose", POSE), (13, "movec", "pose_via", POSE), (13, "movec", "pose_to", POSE),
        (15, "movej", "q", JOINTS), (18, "movel", "pose", POSE), (23, "movel", "pose", RUNTIME)]
    by_line = {(t.line, t.role): t for t in program.targets}
    assert by_line[6, "pose"].values == (0.5, -0.2, 0.4, 0.0, 3.14, 0.0)
    assert by_line[6, "pose"].column == 9
    assert by_line[11, "pose_to"].values == (0.42, -0.3, 0.36, 0.0, 3.1, 0.0)
    assert by_line[13, "pose_to"].values == (0.42, -0.3, 0.36, 0.0, 3.1, 0.0)  # movec's to given by keyword
    assert by_line[15, "q"].values == (0.3, -1.3, 1.2, -1.4, -1.57, 0.5)  # across lines, past a comment
    assert by_line[18, "pose"].values == (0.5, -0.2, 0.41, 0.0, 3.14, 0.0)  # across a line continuation
    assert not any(9.0 in (t.values or ()) for t in program.targets)  # comments, strings, my_movel: no calls


def test_the_set_tcp_in_force_follows_the_program_order():
    program = parse("movel(p[.5,0,.4,0,3.14,0])\nset_tcp(p[0,0,.1,0,0,0])\nmovel(p[.5,0,.4,0,3.14,0])\n"
                    "set_tcp(p[0.01, 0, 0.12, 0, 0, 1.57])\nmovej([0,-1.5,1.5,-1.5,-1.5,0])\n"
                    "set_tcp(tool_for(2))\nmovel(p[.5,0,.4,0,3.14,0])\n", "t.script")
    tcps = [t.tcp for t in program.targets]
    assert tcps[0] is None  # none set yet: the controller's own (--tcp-mm or the calibrated target)
    assert tcps[1].pose == (0.0, 0.0, 0.1, 0.0, 0.0, 0.0) and tcps[1].line == 2
    assert tcps[2].pose == (0.01, 0.0, 0.12, 0.0, 0.0, 1.57) and tcps[2].line == 4
    assert tcps[3].pose is None and tcps[3].line == 6 and tcps[3].source == "tool_for(2)"


@pytest.mark.parametrize("call, why", [
    ("movel(start)", "computed at run time"),
    ("movel(pose_trans(start, p[0, 0, 0.01, 0, 0, 0]))", "computed at run time"),
    ("movej(get_inverse_kin(p[0.5, 0, 0.4, 0, 3.14, 0]))", "computed at run time"),
    ("movel(pose_add(p[0.5, 0, 0.4, 0, 3.14, 0], d))", "computed at run time"),
    ("movel(p[0.5, 0, 0.4, 0, 3.14, 0] )", None),  # a literal with a space before the bracket closes
    ("movel(p[0.5, 0, 0.4 + dz, 0, 3.14, 0])", "computed at run time"),
    ("movel(p[0.5, 0, z, 0, 3.14, 0])", "computed at run time"),
    ("movej([0, -1.5, 1.5, -1.5, -1.5])", "a joint list of 5 values, not 6"),
    ("movel(p[0.5, 0, 0.4])", "a pose of 3 values, not 6"),
    ("movel(a=1.2, v=0.25)", "no pose given"),
])
def test_targets_computed_at_run_time_are_listed_never_guessed(call, why):
    (target,) = parse(f"def p1():\n  {call}\nend\n").targets
    if why is None:
        assert target.kind == POSE
    else:
        assert target.kind == RUNTIME and target.values is None and why in target.reason


@pytest.mark.parametrize("text, where, words", [
    ("movel(p[0.5, 0, 0.4, 0, 3.14, 0]\n", "1:6", "'(' is never closed"),
    ("movel(p[0.5, 0, 0.4, 0, 3.14, 0)\n", "1:32", "')' closes the '[' opened at 1:8"),
    ("def a():\n  movel(p[0.5, 0, 0.4, 0, 3.14, 0]))\nend\n", "2:36", "')' closes nothing"),
    ('textmsg("movel(p[0,0,0,0,0,0])\nmovel(p[0.5, 0, 0.4, 0, 3.14, 0])\n', "1:9", "string opened here is not closed"),
])
def test_a_program_that_cannot_be_read_is_one_error_naming_the_place(text, where, words):
    with pytest.raises(ProgramError) as refused:
        parse(text, "bad.script")
    assert str(refused.value).startswith(f"bad.script:{where}: ") and words in str(refused.value)


def test_the_rewrite_changes_the_targets_numbers_and_not_one_other_byte(tmp_path):
    """CRLF line endings, tabs, comments, speeds and blends, spacing inside the brackets, a byte
    that is not UTF-8: all kept; a number written with DECIMALS decimals reads back to within
    half a unit of the last one."""
    source = (b"def prog():\r\n\t# tool: \xe9querre\r\n\tmovel(p[ .5,-.2 , .4,0,3.14,0 ], a=1.2, v=0.25, r=0.01)"
              b"  # approach\r\n\tmovej([0.1,-1.5,1.4,-1.2,-1.57,0],a=1.4,v=1.05)\r\n\tmovel(here)\r\nend\r\n")
    path = tmp_path / "prog.script"
    path.write_bytes(source)
    program = read_program(path)
    assert encode(rewrite(program.text, {})) == source  # nothing to replace: the very bytes
    pose, joints, runtime = program.targets
    new_pose = (0.5004123456789, -0.19987654321, 0.4000001, 1e-7, 3.1399999, -2.5e-8)
    new_joints = tuple(np.array(joints.values) + 1.234567e-4)
    out = encode(rewrite(program.text, {pose: new_pose, joints: new_joints}))
    back = parse(out.decode("utf-8", errors="surrogateescape"))
    assert encode(without_target_numbers(back)) == encode(without_target_numbers(program))
    assert out.count(b"\r\n") == source.count(b"\r\n") and b"\xe9querre" in out and b"r=0.01)  # approach" in out
    assert np.abs(np.array(back.targets[0].values) - new_pose).max() <= 0.5 * 10.0 ** -DECIMALS
    assert np.abs(np.array(back.targets[1].values) - new_joints).max() <= 0.5 * 10.0 ** -DECIMALS


def without_target_numbers(program) -> str:
    """The program's text with every number of its literal targets replaced by '#': what must stay
    byte for byte when only targets are compensated (speeds, blends, comments, spacing included)."""
    text = program.text
    for n in sorted((n for t in program.targets for n in t.numbers), key=lambda n: -n.start):
        text = text[:n.start] + "#" + text[n.end:]
    return text


@pytest.mark.parametrize("value, text", [(0.0, "0.0"), (-0.0, "0.0"), (1.0, "1.0"), (-0.25, "-0.25"),
                                         (1e-7, "0.0000001"), (-3e-11, "0.0"), (3.14159265358979, "3.1415926536")])
def test_numbers_are_written_as_urscript_reads_them(value, text):
    assert format_number(value) == text


# -- the hidden truth: a robot, its calibration, programs for it -------------------------------------------------

TOOL_MM = np.array([0.0, 0.0, 100.0])
HOME = np.deg2rad([20.0, -100.0, 100.0, -90.0, -90.0, 10.0])


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    """A UR10e with hidden geometric errors, its tool point exactly TOOL_MM from its real flange, and
    its calibration from 1000 tracker-measured poses (enough that the calibrated model's own error is
    well under the 0.02 mm asked of the compensated program: about 0.01 mm)."""
    model = load_robot("ur10e")
    rng = np.random.default_rng(11)
    arm = PhysicalArm(model, rng, [], target_offsets=[TOOL_MM], target_offset_error_mm=0.0)
    data = arm.campaign(full_workspace(model, 1000, rng))
    calibrated = from_fit(model, data.obs.target_names, identify(model, data.obs, IdentifyOptions(regularize="none")).x)
    truth = from_fit(model, arm.target_names, arm.truth.x)
    folder = tmp_path_factory.mktemp("urscript")
    write_calibrated(folder / "cal.yaml", calibrated, "ur10e", {"written_by": "test"})
    return model, calibrated, truth, folder


def _walk(n: int, rng) -> np.ndarray:
    """Joints a program visits: small steps from HOME, as a path through a workpiece takes them."""
    return HOME + np.cumsum(np.deg2rad(rng.uniform(-6.0, 6.0, (n, 6))), axis=0)


def _literal(values, pose: bool) -> str:
    return ("p[" if pose else "[") + ", ".join(f"{v:.6f}" for v in values) + "]"


def every_form_program(model, tool_mm: np.ndarray, seed: int = 3, blocks: int = 4) -> str:
    """A program of every motion form through poses an offline system computed with the nominal model:
    first with the controller's own tool (no set_tcp), then with set_tcp at the tool point, then the
    same point with the tool frame turned. Between them a target computed at run time."""
    q = iter(_walk(blocks * 9, np.random.default_rng(seed)))
    tcps = [None, np.r_[tool_mm / 1000.0, 0.0, 0.0, 0.0], np.r_[tool_mm / 1000.0, 0.1, -0.2, 0.3]]
    lines = ["# every motion form, poses from an offline system (nominal kinematics)", "def cal_test():"]

    def pose(tcp):
        rot, p = tcp_frames(model, next(q), np.r_[tool_mm / 1000.0, 0, 0, 0] if tcp is None else tcp)
        return _literal(np.r_[p[0], se3.matrix_to_rotvec(rot[0])], True)

    for block in range(blocks):
        tcp = tcps[min(block, 2)]
        if block and tcp is not None:
            lines.append(f"  set_tcp({_literal(tcp, True)})  # the tool")
        lines += [f"  movej({_literal(next(q), False)}, a=1.4, v=1.05)",
                  f"  movel({pose(tcp)}, a=1.2, v=0.25, r=0.005)  # approach",
                  f"  movel({_literal(next(q), False)}, a=1.2, v=0.25)",
                  f"  movep({pose(tcp)}, a=1.2, v=0.25, r=0.002)",
                  f"  movec({pose(tcp)}, {pose(tcp)}, a=1.2, v=0.1, r=0, mode=1)",
                  f"  movej({pose(tcp)}, a=1.4, v=1.05, t=0, r=0)",
                  "  movel(pose_trans(get_actual_tcp_pose(), p[0, 0, 0.001, 0, 0, 0]), a=1.2, v=0.25)",
                  f"  movel(pose={pose(tcp)}, v=0.25)"]
    return "\n".join(lines + ["end", "cal_test()", ""])


def drive(program, model, truth, default_tool_mm) -> np.ndarray:
    """Where the real robot's tool point ends at each literal target (instrument frame, mm): the
    controller turns a pose into joints with its nominal model, from the joints it is at, with the
    tool of the set_tcp in force (independently of programs.apply: solvers.geometry.inverse, in metres)."""
    landed, previous = [], None
    for t in program.targets:
        if t.kind == RUNTIME:
            continue  # the test's run-time targets stay within 1 mm of the previous one: no branch change
        tool = np.r_[default_tool_mm / 1000.0, 0, 0, 0] if t.tcp is None else np.array(t.tcp.pose)
        q = np.array(t.values) if t.kind == JOINTS else inverse(model, np.array(t.values), previous, tool)
        assert q is not None, f"line {t.line}: the controller finds no joints for the written pose"
        previous = q
        landed.append(truth.predict(q[None], np.zeros(1, int))[0])
    return np.array(landed)


def meant(program, model, truth, default_tool_mm) -> np.ndarray:
    """Where each literal target means the tool point to be, in the instrument frame: the TCP pose in the
    controller's base frame (a joint target's through the nominal model), placed by the truth's own
    controller frame: the definition the compensation uses (solvers.compensation.compensate.controller_frame), applied
    to the true robot, its real tool point against the tool the controller computes with."""
    controller = solver.controller_frame(truth, model, offset_mm=truth.offsets[0], nominal_offset_mm=default_tool_mm)
    out = []
    for t in program.targets:
        if t.kind == RUNTIME:
            continue
        tool = np.r_[default_tool_mm / 1000.0, 0, 0, 0] if t.tcp is None else np.array(t.tcp.pose)
        if t.kind == JOINTS:
            rot, p = tcp_frames(model, np.array(t.values), tool)
        else:
            rot, p = se3.rotvec_to_matrix(np.array(t.values[3:]))[None], np.array(t.values[:3])[None]
        in_model = solver.targets_in_model_frame(truth, model, p * 1000.0, rot, "base", controller=controller)[0]
        out.append(in_model[0] @ se3.rotvec_to_matrix(truth.base[3:]).T + truth.base[:3])
    return np.array(out)


@pytest.mark.parametrize("blocks, sweeps", [(4, apply.MAX_SWEEPS), (12, 1)], ids=["batched", "row-by-row tail"])
def test_compensated_with_the_true_model_the_program_lands_exactly(robot, monkeypatch, blocks, sweeps):
    """The program's reading alone, without any calibration error: compensated with the truth itself,
    every literal target of every form lands where it is meant to within the solvers' and the
    controller's tolerances (1e-6 mm) and the 1e-10 m of the written digits: 1e-4 mm is far below any
    interpretation error (a wrong tool, frame or branch is mm). The poses' controller joints are solved
    in batched sweeps; with one sweep allowed, most are finished row by row: the same answer."""
    monkeypatch.setattr(apply, "MAX_SWEEPS", sweeps)
    model, _, truth, _ = robot
    program = parse(every_form_program(model, truth.offsets[0], blocks=blocks), "prog.script")
    result = compensate_program(program, model, truth, default_tcp_mm=truth.offsets[0])
    assert [o.status for o in result.per_target].count("ok") == sum(t.kind != RUNTIME for t in program.targets)
    out = parse(rewrite(program.text, result.replacements))
    error = np.linalg.norm(drive(out, model, truth, truth.offsets[0]) - meant(program, model, truth, truth.offsets[0]),
                           axis=1)
    assert error.max() < 1e-4, error


def row_by_row(program, model, calibrated, default_tool_mm):
    """The straightforward reading of a program, the reference for compensate_program: target after target,
    each pose's controller joints by its own nominal inverse from the previous target's, then every target's
    calibrated joints (one solve per target's tool: the solver's rows are independent). {target index:
    (status, values or None)}."""
    out, rows, last = {}, [], None
    for k, t in enumerate(program.targets):
        if t.kind == RUNTIME or (t.tcp is not None and t.tcp.pose is None):
            out[k] = ("runtime" if t.kind == RUNTIME else "tcp_unknown", None)
            continue
        tool = np.r_[default_tool_mm / 1000.0, 0, 0, 0] if t.tcp is None else np.array(t.tcp.pose)
        frames = solver.rigid_frames(model, model.nominal, tool[:3] * 1000.0)
        tool_rot = se3.rotvec_to_matrix(tool[3:])
        if t.kind == JOINTS:
            q = np.array(t.values)
            if ((q < model.joint_limits[:, 0]) | (q > model.joint_limits[:, 1])).any():
                out[k] = ("joint_limits", None)
                continue
            rot, p = frames(q[None], None)[:2]
            position, flange = p[0], rot[0]
        else:
            position = np.array(t.values[:3]) * 1000.0
            flange = se3.rotvec_to_matrix(np.array(t.values[3:])) @ tool_rot.T
            q, done = solver.solve(frames, position[None], flange[None], last[None], max_iter=apply.IK_ITERATIONS)[:2]
            if not done[0]:
                out[k] = ("unreachable", None)
                continue
            q = q[0]
        last = q
        rows.append((k, tuple(tool[:3] * 1000.0), tool_rot, position, flange, q))
    direction = approach_directions(np.array([r[5] for r in rows]))
    controller = solver.controller_frame(calibrated, model, offset_mm=default_tool_mm)
    for tool in dict.fromkeys(r[1] for r in rows):
        group = [j for j, r in enumerate(rows) if r[1] == tool]
        xyz, rot = solver.targets_in_model_frame(calibrated, model, np.array([rows[j][3] for j in group]),
                                                 np.array([rows[j][4] for j in group]), "base", controller=controller)
        result = solver.compensate(model, calibrated, xyz, rot, np.array([rows[j][5] for j in group]),
                                   offset_mm=np.array(tool), controller=controller,
                                   ctx_at=lambda q, which, d=direction[group]: Context(direction=d[which]))
        for g, j in enumerate(group):
            k, _, tool_rot, _, _, _ = rows[j]
            target = program.targets[k]
            values = None
            if result.status[g] == "ok" and target.kind == JOINTS:
                values = result.q[g]
            elif result.status[g] == "ok":
                r = se3.matrix_to_rotvec(result.rotation[g] @ tool_rot)
                other = r * (1.0 - 2.0 * np.pi / np.linalg.norm(r))  # the same turn the other way round
                written = np.array(target.values[3:])
                near = r if np.linalg.norm(r - written) <= np.linalg.norm(other - written) else other
                values = np.r_[result.position_mm[g] / 1000.0, near]
            out[k] = (str(result.status[g]), values)
    return out


@pytest.mark.parametrize("sweeps, chunk", [(apply.MAX_SWEEPS, apply.CHUNK_ROWS), (1, 7)],
                         ids=["sweeps", "row-by-row tail, chunks of 7"])
def test_the_batched_program_gives_the_row_by_row_answer(robot, monkeypatch, sweeps, chunk):
    """compensate_program solves all poses at once, sweep after sweep, finishes what has not settled row
    by row, and compensates the targets in chunks: the answer is the straightforward one, target after
    target. A program of four tools (one set at run time), joint and pose targets, targets computed at run
    time, a pose 3 m away (the controller's own model does not reach it: the next pose is solved from the
    target before it) and a joint target outside the limits, its paths up to 80 poses long between joint
    targets (far more than the sweeps settle). Statuses equal, values to 1e-10 (m and rad): the solvers stop
    at 1e-7 mm and 1e-10 rad, and a pose solved from a seed that moved by under SEED_MOVED_RAD lands on the
    same solution to that tolerance."""
    monkeypatch.setattr(apply, "MAX_SWEEPS", sweeps)
    monkeypatch.setattr(apply, "CHUNK_ROWS", chunk)
    model, calibrated, _, _ = robot
    text = long_program(model, calibrated.offsets[0], lines=180, seed=2).replace(
        "  sleep(0.01)  # station 1 done", "  movel(p[3.0, 0.0, 0.5, 0.0, 3.14, 0.0])  # 3 m away\n"
        "  movej([0.35, -1.7, 1.7, -1.57, -1.57, 6.5])  # joint 6 beyond 360 deg\n  sleep(0.01)").replace(
        "\nend\n", "\n  set_tcp(tool_of(2))\n  movel(p[0.5, -0.2, 0.4, 0, 3.14, 0])\nend\n")
    program = parse(text, "long.script")
    result = compensate_program(program, model, calibrated, default_tcp_mm=calibrated.offsets[0])
    want = row_by_row(program, model, calibrated, calibrated.offsets[0])
    got = {k: (o.status, o.values) for k, o in enumerate(result.per_target)}
    assert [s for s, _ in got.values()] == [want[k][0] for k in got]
    assert {"ok", "runtime", "tcp_unknown", "unreachable", "joint_limits"} <= {s for s, _ in got.values()}
    difference = max(np.abs(np.subtract(v, want[k][1])).max() for k, (s, v) in got.items() if s == "ok")
    assert difference <= 1e-10, difference


def test_a_compensated_program_lands_within_0_02_mm_on_the_hidden_robot(robot, capsys):
    """The whole command: cal.yaml and a program of every form in, the compensated program out, driven
    on the true robot as its controller would. The program's tool is the calibrated target (the point
    the tracker saw); the controller's own tool (no set_tcp) is that point as well."""
    model, calibrated, truth, folder = robot
    text = every_form_program(model, calibrated.offsets[0])
    (folder / "prog.script").write_text(text)
    out = folder / "prog-cal.script"
    assert main(["compensate", "--robot", str(folder / "cal.yaml"), "--program", str(folder / "prog.script"),
                 "-o", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    program, compensated = parse(text), parse(out.read_text())
    literal = sum(t.kind != RUNTIME for t in program.targets)
    assert report["compensated"] == literal and report["not_compensated"] == {"runtime": 4}
    assert [r["status"] for r in report["report"] if r["kind"] == RUNTIME] == ["runtime"] * 4
    want = meant(program, model, truth, calibrated.offsets[0])
    as_written = np.linalg.norm(drive(program, model, truth, calibrated.offsets[0]) - want, axis=1).mean()
    after = np.linalg.norm(drive(compensated, model, truth, calibrated.offsets[0]) - want, axis=1).mean()
    # 0.02 mm: what the issue asks; the calibrated model's own error here is about 0.01 mm
    assert after <= 0.02, (after, as_written)
    assert as_written > 20.0 * after, (after, as_written)  # hidden errors of 0.5 mm / 0.05 deg: about 1 mm
    # every other byte as it was, and one line added last (every line keeps its number): the marker naming the
    # model, which a second compensation refuses
    *body, marker = out.read_text().splitlines(keepends=True)
    assert marker.startswith("# cellcal compensated: with cal.yaml (sha256 ") and "nominal ur10e" in marker, marker
    assert without_target_numbers(parse("".join(body))) == without_target_numbers(program)
    # a correction above --max-correction-deg is compensated all the same, with a warning naming the line
    assert main(["compensate", "--robot", str(folder / "cal.yaml"), "--program", str(folder / "prog.script"),
                 "-o", str(out), "--max-correction-deg", "1e-6"]) == 0
    err = capsys.readouterr().err
    assert "prog.script:4: warning: compensated, but the joints move by" in err
    assert parse(out.read_text()).targets == compensated.targets


def test_a_compensated_program_or_target_file_is_not_compensated_again_without_force(robot, tmp_path, capsys):
    """Compensating twice moves every target a second time (about the calibration's correction again):
    the output's marker makes a second run refuse, status 2, nothing written; --force does it and says so."""
    model, calibrated, truth, folder = robot
    (tmp_path / "prog.script").write_text(every_form_program(model, calibrated.offsets[0]))
    once, twice = tmp_path / "once.script", tmp_path / "twice.script"
    base = ["compensate", "--robot", str(folder / "cal.yaml")]
    assert main(base + ["--program", str(tmp_path / "prog.script"), "-o", str(once)]) == 0
    capsys.readouterr()
    assert main(base + ["--program", str(once), "-o", str(twice)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "once.script: already compensated (with cal.yaml (sha256" in err, err
    assert "--force" in err and not twice.exists()
    assert main(base + ["--program", str(once), "-o", str(twice), "--force", "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["compensated_before"].startswith("cellcal compensated: with cal.yaml")
    assert "compensated before" in captured.err and twice.read_text().count("# cellcal compensated:") == 2
    # a target file: its rows carry the marker in a column, and the output is refused as input alike
    targets, out, again = tmp_path / "t.csv", tmp_path / "t-cal.csv", tmp_path / "t-cal-cal.csv"
    targets.write_text("x_mm,y_mm,z_mm,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n"
                       "600,-150,400,20,-100,100,-90,-90,0\n")
    assert main(base + ["--targets", str(targets), "-o", str(out)]) == 0
    capsys.readouterr()
    assert main(base + ["--targets", str(out), "-o", str(again)]) == 2
    assert "t-cal.csv: already compensated" in capsys.readouterr().err and not again.exists()


UNREACHABLE_PROGRAM = """\
movej([0.35, -1.75, 1.75, -1.57, -1.57, 0.2], a=1.4, v=1.05)
movel(p[3.0, 0.0, 0.5, 0.0, 3.14, 0.0], a=1.2, v=0.25)  # 3 m away: beyond a UR10e's 1.3 m
movel([0.35, -1.7, 1.7, -1.57, -1.57, 0.2], a=1.2, v=0.25)
movej([0.35, -1.7, 1.7, -1.57, -1.57, 6.5], a=1.4, v=1.05)  # joint 6 at 372 deg: beyond +-360
"""


def test_targets_out_of_reach_are_listed_and_nothing_is_written_without_allow_partial(robot, tmp_path, capsys):
    model, calibrated, truth, folder = robot
    prog, out = tmp_path / "reach.script", tmp_path / "reach-cal.script"
    prog.write_text(UNREACHABLE_PROGRAM)
    argv = ["compensate", "--robot", str(folder / "cal.yaml"), "--program", str(prog), "-o", str(out)]
    assert main(argv + ["--json"]) == 1
    captured = capsys.readouterr()
    report = json.loads(captured.out)
    assert [(r["line"], r["status"]) for r in report["report"]] == [
        (1, "ok"), (2, "unreachable"), (3, "ok"), (4, "joint_limits")]
    assert report["written"] is False and report["error"]["code"] == 1 and "--allow-partial" in captured.err
    assert not out.exists()

    assert main(argv + ["--allow-partial"]) == 0
    text = capsys.readouterr().out
    assert "reach.script:2: movel (pose): unreachable" in text
    assert "reach.script:4: movej (joints): joint_limits" in text
    written = out.read_text().splitlines()
    source = UNREACHABLE_PROGRAM.splitlines()
    assert written[1] == source[1] and written[3] == source[3]  # left as written
    assert written[0] != source[0] and written[2] != source[2]  # compensated


def test_a_joint_target_of_1e300_is_outside_the_joint_limits_and_no_numpy_warning_is_shown(robot, tmp_path,
                                                                                               capsys):
    folder = robot[3]
    argv = _cli(folder, tmp_path, "movej([1e300, -1.75, 1.75, -1.57, -1.57, 0.2])\n" + GOOD, "--json")
    assert main(argv) == 1
    captured = capsys.readouterr()
    report = json.loads(captured.out)["report"]
    assert [(r["line"], r["status"]) for r in report] == [(1, "joint_limits"), (2, "ok")], report
    assert "joint 1 at 5.72958e+301 deg is outside its limits" in report[0]["reason"], report[0]
    assert "Warning" not in captured.err and "Traceback" not in captured.err, captured.err


def test_a_program_without_a_motion_target_is_said_to_have_nothing_compensated(robot, tmp_path, capsys):
    argv = _cli(robot[3], tmp_path, "# only a comment\npopup(\"hello\")\n")
    assert main(argv) == 0
    out, err = capsys.readouterr()
    assert "compensated 0 of 0 targets" in out
    assert "p.script: warning: no movej, movel, movep or movec target in the program" in err, err


def _cli(folder, tmp_path, text, *extra):
    prog = tmp_path / "p.script"
    prog.write_text(text)
    return ["compensate", "--robot", str(folder / "cal.yaml"), "--program", str(prog), "-o",
            str(tmp_path / "out.script"), *extra]


GOOD = "movej([0.35, -1.75, 1.75, -1.57, -1.57, 0.2])\n"
BAD_INPUT = [  # (name, program text, extra options, words in the one message)
    ("an unclosed bracket", "movel(p[0.5, 0, 0.4, 0, 3.14, 0]\n", (), ["p.script:1:6: '(' is never closed"]),
    ("an unterminated string", 'popup("movel(p[0,0,0,0,0,0])\n', (), ["p.script:1:7: a string opened here"]),
    ("a pose before any joints", "movel(p[0.5, 0, 0.4, 0, 3.14, 0])\n", (), ["p.script:1:7:", "--seed-deg"]),
    ("a number no double holds", GOOD + "movel(p[1e400, 0, 0.4, 0, 3.14, 0])\n", (),
     ["p.script:2:9: 1e400 is beyond any number the controller holds"]),
    ("a binary file", GOOD + "\x7fELF\x02\x01\x00[(\x00\x00", (), ["p.script: not a text program (a NUL byte on line 2"]),
    ("the output into a folder that is not there", None, (), ["out/p-cal.script: the folder", "/out does not exist"]),
    ("a seed of 5 joints", GOOD, ("--seed-deg", "0", "-90", "90", "-90", "-90"), ["--seed-deg: give 6"]),
    ("--unit with a program", GOOD, ("--unit", "deg"), ["--unit", "radians"]),
    ("--allow-partial with a CSV", None, (), ["--allow-partial: only with --program"]),
    ("the output is the program", None, (), ["is the program itself"]),
    ("a program that does not exist", None, (), ["missing.script: cannot read the program"]),
    ("the output into /proc", None, (), ["-o /proc/p-cal.script: cannot create the file"]),
]


@pytest.mark.parametrize("name, text, extra, words", BAD_INPUT, ids=[c[0] for c in BAD_INPUT])
def test_bad_input_is_one_message_and_nothing_written(robot, tmp_path, capsys, name, text, extra, words):
    folder = robot[3]
    if name == "--allow-partial with a CSV":
        argv = ["compensate", "--robot", str(folder / "cal.yaml"), "--targets", str(tmp_path / "t.csv"), "-o",
                str(tmp_path / "out.script"), "--allow-partial"]
    elif name == "the output is the program":
        argv = _cli(folder, tmp_path, GOOD)
        argv[-1] = argv[-3]
    elif name == "the output into /proc":  # checked before anything is read or computed
        argv = _cli(folder, tmp_path, GOOD)
        argv[-1] = "/proc/p-cal.script"
    elif name == "the output into a folder that is not there":
        argv = _cli(folder, tmp_path, GOOD)
        argv[-1] = str(tmp_path / "out" / "p-cal.script")
    elif name == "a program that does not exist":
        argv = _cli(folder, tmp_path, GOOD)
        argv[-3] = str(tmp_path / "missing.script")
    else:
        argv = _cli(folder, tmp_path, text, *extra)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and "Traceback" not in err, err
    for w in words:
        assert w in err, err
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # nothing written, nothing changed


def test_a_pose_first_is_solved_from_seed_deg_and_a_tool_set_at_run_time_is_listed(robot, tmp_path, capsys):
    folder = robot[3]
    text = ("movel(p[0.6, -0.2, 0.5, 0, 3.14, 0])\nset_tcp(tool)\nmovel(p[0.6, -0.2, 0.45, 0, 3.14, 0])\n"
            "movej([0.35, -1.75, 1.75, -1.57, -1.57, 0.2])\n")
    assert main(_cli(folder, tmp_path, text, "--seed-deg", "-20", "-80", "90", "-100", "-90", "0", "--json")) == 0
    report = json.loads(capsys.readouterr().out)
    assert [r["status"] for r in report["report"]] == ["ok", "tcp_unknown", "tcp_unknown"]
    assert "line 2 (set_tcp(tool))" in report["report"][1]["reason"]
    assert report["written"] is True and report["not_compensated"] == {"tcp_unknown": 2}
