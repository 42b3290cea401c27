"""tcp-stylus: a cylindrical tool touched on a stylus ball, scored against the simulation's
hidden truth (the real tool is a capsule off its drawing, the ball off where the file says).

Errors against the truth: the axis line's distance from the true one at the true tip (mm),
the angle between the axes (deg), and the TCP's full 3-D error (mm; its place along the axis
comes from the end-face touches). The turn about the axis is not measured (the frame keeps the
controller's), not scored.
"""
from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

from cellcal.config.robot_files import load_robot
from cellcal.daemon.cells import load_cell, open_drivers
from cellcal.routines.framework import registry, runner
from cellcal.routines.framework.base import RoutineError
from cellcal.routines.framework.guard import GuardedRobot
from cellcal.solvers.geometry import se3
from cellcal.solvers.tool_frames import stylus as fitting
from cellcal.solvers.tool_frames import stylus_design as design
from cellcal.solvers.geometry.inverse import inverse, tcp_frames, tcp_poses
from support.cell_edits import edited_cell  # tests/support/cell_edits.py
from support.report_check import assert_report_draws, layer

AXIS_MM, AXIS_DEG, TCP_MM = 0.02, 0.01, 0.03  # targets with at most 200 contacts
Q = [f"q{i}_rad" for i in range(1, 7)]


def errors(tool_frame, truth) -> dict:
    frame = np.asarray(tool_frame, float)
    u = se3.rotvec_to_matrix(frame[3:])[:, 2]
    d = truth.tool.tcp_m * 1e3 - frame[:3] * 1e3
    return {"axis_mm": float(np.linalg.norm(d - (d @ u) * u)), "tcp_mm": float(np.linalg.norm(d)),
            "axis_deg": float(np.degrees(np.arccos(np.clip(u @ truth.tool.axis, -1.0, 1.0))))}


def run(cell, out_dir, noise_seed=None):
    """The routine end to end; also every cycle at which the tool began to touch the stylus
    outside a contact search (there must be none). `noise_seed`: draw the arm's repeatability
    afresh (every simulated cell draws the same sequence otherwise)."""
    prepared = runner.prepare("tcp-stylus", cell)
    with open_drivers(cell) as drivers:
        world, robot, state = drivers.world, drivers.robot, {"search": False, "was": False, "new": []}
        if noise_seed is not None:
            world.rng = np.random.default_rng(noise_seed)
        step, search = world.step, robot.move_until_contact

        def watched_step():
            step()
            now = world.touching()
            if now and not state["was"] and not state["search"]:
                state["new"].append(world.t_s)
            state["was"] = now

        def watched_search(*args, **kwargs):
            state["search"] = True
            try:
                return search(*args, **kwargs)
            finally:
                state["search"] = False

        world.step, robot.move_until_contact = watched_step, watched_search
        dataset = runner.measure(prepared, drivers, out_dir, lambda message: None)
        truth = world.truth
    return runner.solve("tcp-stylus", cell, dataset), dataset, truth, state["new"]


def variant(tmp_path, name, changes):
    """The sim cell with `changes` (tests/support/cell_edits.py) to its file."""
    return load_cell(edited_cell(tmp_path, "sim", changes, name=f"{name}.yaml"))


@pytest.fixture(scope="module")
def default_run(tmp_path_factory):
    cell = load_cell("sim")
    return (cell, *run(cell, tmp_path_factory.mktemp("stylus")))


def test_the_default_cell_meets_the_targets_against_the_hidden_truth(default_run):
    cell, result, dataset, truth, _ = default_run
    e = errors(result.tool_frame, truth)
    assert len(dataset) <= 200
    assert e["axis_mm"] <= AXIS_MM and e["axis_deg"] <= AXIS_DEG and e["tcp_mm"] <= TCP_MM, e
    assert result.passed_gates, result.reasons()
    assert np.linalg.norm(np.array(result.extra["stylus_mm"]) - truth.stylus.centre_m * 1e3) <= 0.05
    assert abs(result.extra["contact_radius_mm"] - (truth.tool.radius_m + truth.stylus.radius_m) * 1e3) <= 0.05
    # the reported spread is the real one: the errors lie within 4 standard deviations
    std = {p.name: p.std for p in result.parameters}
    tip = {p.name: p.value for p in result.parameters}
    for i, axis in enumerate("xyz"):
        assert abs(tip[f"tcp.{axis}"] - truth.tool.tcp_m[i] * 1e3) <= 4 * std[f"tcp.{axis}"] + 1e-3
    # what the command prints: sim_truth's position is the TCP's, its angle the axis'
    score = truth.score_tool_frame(result.tool_frame)
    assert score["position_error_mm"] == pytest.approx(e["tcp_mm"], abs=1e-9)
    assert score["axis_error_deg"] == pytest.approx(e["axis_deg"], abs=1e-9)


def test_the_recorded_contacts_sit_on_the_real_tool_to_the_arms_repeatability(default_run):
    """The sim notices a contact once per 2 ms cycle; searched again at 2 mm/s and with the
    mean half cycle taken off, the recorded contacts lie on the real capsule and ball with no
    bias beyond a few micrometres, scattered as the arm's repeatability (0.03 mm RMS in 3-D,
    0.017 mm along a contact's normal)."""
    cell, result, dataset, truth, _ = default_run
    data = design.Recorded.of(load_robot(cell.robot), dataset.stack(*Q), dataset["kind"], dataset["group"],
                              dataset.stack("dir_x", "dir_y", "dir_z"), dataset["speed_m_s"], dataset.meta["cycle_s"])
    r_s, radius = truth.stylus.radius_m * 1e3, (truth.tool.radius_m + truth.stylus.radius_m) * 1e3
    real = fitting.Setup(fitting.Line(truth.tool.tcp_m * 1e3, truth.tool.axis), r_s, radius, True, "round")
    r = fitting.residuals(np.r_[0, 0, 0, 0, truth.stylus.centre_m * 1e3, radius, 0.0],
                          data.contacts(data.kind != "coarse-face"), real, True)
    assert abs(np.mean(r)) < 0.004 and np.sqrt(np.mean(r ** 2)) < 0.022, (np.mean(r), np.sqrt(np.mean(r ** 2)))
    assert dataset.meta["cycle_s"] == pytest.approx(0.002)


def test_every_contact_is_a_search_and_the_tool_touches_nothing_on_the_way(default_run):
    *_, touched_outside = default_run
    assert touched_outside == []


def test_the_result_says_what_the_data_cannot_measure(default_run):
    _, result, *_ = default_run
    names = [p.name for p in result.parameters]
    assert "tcp.z" in names and not any("rz" in n for n in names)  # the turn about the axis is no result
    assert any("can measure its turn about the axis" in n for n in result.notes)
    assert any("turn of the tool frame about the tool axis is not measured" in n and "kept from" in n
               for n in result.notes)
    assert any("fixed by 8 end-face touches" in n for n in result.notes)
    assert result.extra["rank"] == len(result.extra["fitted"]) == 9


def test_a_recorded_run_solves_again_to_the_same_frame(default_run):
    cell, result, dataset, *_ = default_run
    again = runner.solve_file("tcp-stylus", cell, dataset.path)
    np.testing.assert_allclose(again.tool_frame, result.tool_frame, atol=1e-12)


def test_without_end_face_touches_the_tcp_along_the_axis_is_a_stated_convention(default_run):
    cell, result, dataset, truth, _ = default_run
    sides = copy.deepcopy(dataset)
    keep = sides["kind"] != "face"
    sides.columns = {k: v[keep] for k, v in sides.columns.items()}
    alone = runner.solve("tcp-stylus", cell, sides)
    names = [p.name for p in alone.parameters]
    assert not any(n.startswith("tcp.") for n in names) and "axis_near_drawn_tip.x" in names
    assert any("not measured" in n and "convention" in n for n in alone.notes)
    assert alone.extra["tcp_along_axis"].startswith("convention")
    e = errors(alone.tool_frame, truth)  # the axis itself is as good as before
    assert e["axis_mm"] <= AXIS_MM and e["axis_deg"] <= AXIS_DEG


def push(dataset, rows, cell, rng, low_mm=3.0, high_mm=6.0):
    """Gross outliers: contacts recorded 3-6 mm off along their contact normal, in or out."""
    model = load_robot(cell.robot)
    out = copy.deepcopy(dataset)
    for i in rows:
        q = np.array([out[c][i] for c in Q])
        pose = tcp_poses(model, q, cell.tool.tcp_pose)[0]
        normal = np.array([out[c][i] for c in ("dir_x", "dir_y", "dir_z")])
        pose[:3] += normal * rng.choice([-1.0, 1.0]) * rng.uniform(low_mm, high_mm) / 1e3
        for c, v in zip(Q, inverse(model, pose, q, cell.tool.tcp_pose)):
            out.columns[c][i] = v
    return out


def without(dataset, rows):
    out = copy.deepcopy(dataset)
    keep = np.ones(len(dataset), bool)
    keep[rows] = False
    out.columns = {k: v[keep] for k, v in out.columns.items()}
    return out


def assert_same_fit(tool_frame, result):
    """tool_frame is result's, as far as two fits of the same kept contacts can tell: a fit stops once a
    step gains less than ftol = 1e-12 of its cost, so up to ftol * cost above the minimum, which leaves each
    parameter up to sqrt(ftol dof) of its standard deviation off (|J dx|^2 <= 2 ftol cost, std^2 = 2 cost /
    dof (J'J)^-1); twice that for two fits: ~2e-10 m and ~1.3e-9 rad here. Where a fit stops depends on
    the BLAS kernel; the runs seen have ended up to 3e-12 m and 3e-11 rad apart."""
    std = {p.name: p.std * (1e-3 if p.unit == "mm" else np.pi / 180.0) for p in result.parameters}
    stop = 2.0 * np.sqrt(1e-12 * (len(result.residuals_mm) - len(result.extra["fitted"])))
    np.testing.assert_allclose(tool_frame[:3], result.tool_frame[:3], atol=stop * max(std[f"tcp.{c}"] for c in "xyz"))
    np.testing.assert_allclose(tool_frame[3:], result.tool_frame[3:], atol=stop * max(std["tool.rx"], std["tool.ry"]))


def test_ten_percent_gross_outliers_are_left_out(default_run):
    """10 % of the contacts pushed 3-6 mm off the cylinder (as the seed's Table 8 defines an
    outlier): the robust fit leaves out exactly those, so its result is the plain fit of the
    other 90 %; over draws its error is within 1.2x the clean one (plus 0.001 mm or deg for
    the contacts lost). Plain least squares on the same data is refused by its own gates and
    far off (the seed's Table 8: 2.69 mm at 10 %)."""
    cell, clean, dataset, truth, _ = default_run
    plain = dataclasses.replace(registry.read_options("tcp-stylus", cell), loss="linear")
    cls = registry.routine_class("tcp-stylus")
    rng = np.random.default_rng(3)
    clean_e, robust_e = errors(clean.tool_frame, truth), []
    candidates = np.flatnonzero(dataset["kind"] != "coarse-face")
    for _ in range(5):
        rows = rng.choice(candidates, len(dataset) // 10, replace=False)
        spoilt = push(dataset, rows, cell, rng)
        result = runner.solve("tcp-stylus", cell, spoilt)
        assert result.extra["contacts"]["left_out"] == len(rows) and result.passed_gates, result.reasons()
        rest = cls.solve(without(dataset, rows), cell, plain)
        assert_same_fit(result.tool_frame, rest)
        robust_e.append(errors(result.tool_frame, truth))
        least = cls.solve(spoilt, cell, plain)  # plain least squares: refused by its gates, and far off
        assert not least.passed_gates
        assert least.tool_frame is None or errors(least.tool_frame, truth)["axis_mm"] > 5 * clean_e["axis_mm"]
    for key in ("axis_mm", "axis_deg", "tcp_mm"):
        assert np.mean([e[key] for e in robust_e]) <= 1.2 * clean_e[key] + 1e-3, (key, robust_e, clean_e)


def test_ten_percent_more_contacts_gone_wrong_change_nothing(default_run):
    """The same contacts and 10 % more that went 3-6 mm wrong: the clean result, exactly."""
    cell, clean, dataset, truth, _ = default_run
    rng = np.random.default_rng(4)
    extra = rng.choice(np.flatnonzero(dataset["kind"] != "coarse-face"), len(dataset) // 10, replace=False)
    more = copy.deepcopy(dataset)
    more.columns = {k: np.concatenate([v, v[extra]]) for k, v in dataset.columns.items()}
    result = runner.solve("tcp-stylus", cell, push(more, np.arange(len(dataset), len(more)), cell, rng))
    assert result.extra["contacts"]["left_out"] == len(extra) and result.passed_gates
    assert_same_fit(result.tool_frame, clean)


def test_outliers_among_the_coarse_touches_do_not_spoil_the_start(default_run):
    """Two of the four four-point touches 5 mm off put the coarse TCP centimetres away; the fit
    also starts from the drawing and keeps the better, so the result is the clean one."""
    cell, clean, dataset, truth, _ = default_run
    rows = np.flatnonzero(dataset["kind"] == "coarse-face")[:2]
    spoilt = push(dataset, rows, cell, np.random.default_rng(0), 5.0, 5.0)
    data = design.Recorded.of(load_robot(cell.robot), spoilt.stack(*Q), spoilt["kind"], spoilt["group"],
                              spoilt.stack("dir_x", "dir_y", "dir_z"), spoilt["speed_m_s"], spoilt.meta["cycle_s"])
    start = fitting.coarse(data.rotation, data.position_mm, data.kind, data.group, data.approach, 0.5, 3.5,
                           cell.tool.axis)
    assert np.linalg.norm(start.tip_mm - truth.tool.tcp_m * 1e3) > 5.0
    assert_same_fit(runner.solve("tcp-stylus", cell, spoilt).tool_frame, clean)


def test_a_stylus_out_of_reach_stops_at_the_first_contact_with_one_message(tmp_path):
    cell = variant(tmp_path, "far", {"sim_truth": {"fixture_error_mm": 40.0}})
    prepared = runner.prepare("tcp-stylus", cell)
    with open_drivers(cell) as drivers:
        sent = []
        real_run = GuardedRobot.run

        def recording(self, move):
            sent.append(move)
            return real_run(self, move)

        GuardedRobot.run = recording
        try:
            with pytest.raises(RoutineError) as err:
                runner.measure(prepared, drivers, tmp_path / "out", lambda message: None)
        finally:
            GuardedRobot.run = real_run
    assert str(err.value).startswith("contact 1 found nothing within 13.0 mm: is the stylus where [stylus] says?")
    assert sent[-1].label == "contact 1 (coarse-face): search"  # nothing moved after it
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())


def test_options_are_bounded_naming_the_key(tmp_path):
    from cellcal.config.cells import CellFileError

    with pytest.raises(CellFileError, match=r"\[tcp_stylus.heights_mm\].*below its length"):
        variant(tmp_path, "long", {"tcp_stylus": {"heights_mm": [8, 120]}})
    with pytest.raises(CellFileError, match=r"\[tcp_stylus.loss\]"):
        variant(tmp_path, "loss", {"tcp_stylus": {"loss": "tukey"}})


@pytest.mark.slow
@pytest.mark.parametrize("seed", [11, 23, 42])
def test_other_cells_meet_the_targets_too(tmp_path, seed):
    cell = variant(tmp_path, f"seed{seed}", {"sim_truth": {"seed": seed}})
    result, dataset, truth, touched = run(cell, tmp_path, noise_seed=seed)
    e = errors(result.tool_frame, truth)
    assert len(dataset) <= 200 and not touched and result.passed_gates, result.reasons()
    assert e["axis_mm"] <= AXIS_MM and e["axis_deg"] <= AXIS_DEG and e["tcp_mm"] <= TCP_MM, e


# -- the solver on made-up contacts ----------------------------------------------------------------

def synthetic(n=120, seed=0, noise_mm=0.0, spread_deg=360.0, faces=6):
    """Contacts of a known tool and stylus: flange poses built so that the ball touches the
    mantle at chosen heights and angles round it, and the end face on the axis."""
    rng = np.random.default_rng(seed)
    u = np.array([0.01, -0.02, 1.0])
    u /= np.linalg.norm(u)
    tip, stylus, r_s, radius = np.array([0.4, -0.3, 150.2]), np.array([-550.0, -400.0, 400.0]), 0.5, 3.5
    e1 = np.cross(u, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    rot = se3.rotvec_to_matrix(rng.normal(size=(n + faces, 3)) * 0.6)
    kind = np.r_[np.zeros(n, int), np.ones(faces, int)]
    phi = np.radians(rng.uniform(-spread_deg / 2, spread_deg / 2, n + faces))
    h = rng.uniform(8, 90, n + faces)
    point = tip - h[:, None] * u + radius * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    point[n:] = tip + r_s * u  # the ball's centre in the flange frame at each contact
    point += rng.normal(0, noise_mm, point.shape) * (noise_mm > 0)
    position = stylus - np.einsum("nij,nj->ni", rot, point)
    return fitting.Contacts(rot, position, kind), fitting.Line(tip, u), stylus, r_s, radius


def test_the_fit_recovers_a_known_tool_exactly_from_a_start_a_millimetre_off():
    contacts, line, stylus, r_s, radius = synthetic()
    start = fitting.Line(line.point_mm + [0.8, -0.5, 0.3], np.array([0.0, 0.0, 1.0]))
    for shape in ("flat", "round"):
        result = fitting.fit(contacts, fitting.Setup(start, r_s, 3.0, True, shape), stylus + [1, -1, 0.5])
        np.testing.assert_allclose(result.tip_mm, line.point_mm, atol=1e-7)
        assert np.linalg.norm(np.cross(result.line.direction, line.direction)) < 1e-9
        np.testing.assert_allclose(result.stylus_mm, stylus, atol=1e-7)
        assert result.radius_mm == pytest.approx(radius, abs=1e-8)


def test_the_analytic_jacobian_is_the_derivative():
    contacts, line, stylus, r_s, _ = synthetic(30)
    for shape in ("flat", "round"):
        setup = fitting.Setup(fitting.Line(line.point_mm, np.array([0.0, 0.0, 1.0])), r_s, 3.5, True, shape)
        x = np.r_[0.1, -0.2, 0.003, -0.002, stylus + 0.3, 3.4, 0.2]
        _, j = fitting.residuals(x, contacts, setup, True, jac=True)
        h = np.eye(len(x)) * 1e-6
        numeric = np.stack([(fitting.residuals(x + d, contacts, setup, True) -
                             fitting.residuals(x - d, contacts, setup, True)) / 2e-6 for d in h], axis=1)
        np.testing.assert_allclose(j, numeric, atol=1e-6)


def test_coarse_four_point_and_axial_moves_are_exact_on_exact_data():
    rng = np.random.default_rng(1)
    t, p = np.array([1.0, -2.0, 150.0]), np.array([-500.0, -300.0, 420.0])
    rot = se3.rotvec_to_matrix(rng.normal(size=(4, 3)) * 0.4)
    point, fixed, closure = fitting.four_point(rot, p - np.einsum("nij,j->ni", rot, t))
    np.testing.assert_allclose(point, t, atol=1e-8)
    np.testing.assert_allclose(fixed, p, atol=1e-8)
    u = np.array([0.02, 0.01, 1.0]) / np.linalg.norm([0.02, 0.01, 1.0])
    r = np.repeat(rot[:2], 3, axis=0)
    shift = np.array([0.0, 20.0, 40.0] * 2)[:, None] * np.einsum("nij,j->ni", r, u)
    found = fitting.axis_from_axial_moves(r, p - shift, np.repeat([0, 1], 3), np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(found, u, atol=1e-10)


def test_contacts_on_one_generatrix_leave_the_axis_free_across_it():
    """All contacts on one line of the mantle: moving or tilting the axis sideways (across the
    touched side) changes their distances only to second order, and the axis' offset toward
    that side trades against the radius. The rank says so, and names them."""
    contacts, line, stylus, r_s, radius = synthetic(spread_deg=0.0, faces=0)
    seen = design.determined(fitting.fit(contacts, fitting.Setup(line, r_s, radius, True, "round"), stylus))
    assert (seen.rank, seen.n_params) == (5, 8)
    # offset1 and the radius trade one for one; which of the two is written first is arbitrary (see null_terms)
    dirs = [null_terms(w) for w in seen.undetermined]
    want = [{"axis.offset1_mm": 1.0, "radius_mm": -1.0}, {"axis.offset2_mm": 1.0}, {"axis.tilt2_rad": 1.0}]
    assert len(dirs) == 3 and all(any(up_to_sign(d, w) for d in dirs) for w in want), seen.undetermined
    known = design.determined(fitting.fit(contacts, fitting.Setup(line, r_s, radius, False, "round"), stylus))
    assert (known.rank, known.n_params) == (5, 7) and "radius_mm" not in " ".join(known.undetermined)
    spread = design.determined(fitting.fit(synthetic(faces=0)[0], fitting.Setup(line, r_s, radius, True, "round"),
                                           stylus))
    assert spread.rank == spread.n_params == 8 and not spread.undetermined


# -- the seed's 29 parameters on its PUMA 560 scenario ---------------------------------------------

def puma_contacts(where: str, n: int = 40, seed: int = 0):
    """Joints at which the seed's tool (frame 125, 7, 41 mm off the flange, its cylinder's axis
    along the frame's x, radius 20 mm below its origin) touches one stylus point, the tool's
    orientation drawn within +-45 deg of one attitude. `where` on the tool: 'spread' (round
    the cylinder and +-30 mm along it), 'generatrix' (along one line of the mantle) or
    'point' (always the frame's origin, as in the seed's simulation)."""
    from scipy.spatial.transform import Rotation

    model = load_robot("puma560")
    rng = np.random.default_rng(seed)
    q0 = np.radians([0.0, 45.0, -180.0, 0.0, 45.0, 0.0])
    tool = np.array([125.0, 7.0, 41.0, 0.0, 0.0, 0.0])
    rot0, stylus = tcp_frames(model, q0, np.r_[tool[:3] / 1e3, tool[3:]])
    qs = []
    while len(qs) < n:
        x, phi = rng.uniform(-30, 30), rng.uniform(-np.pi, np.pi)
        if where != "spread":
            phi = 0.0
            x = 0.0 if where == "point" else x
        on_tool = tool[:3] + np.array([x, 20.0 * np.sin(phi), -20.0 + 20.0 * np.cos(phi)])
        turn = Rotation.from_euler("xyz", rng.uniform(-45, 45, 3), degrees=True).as_matrix()
        q = inverse(model, np.r_[stylus[0], se3.matrix_to_rotvec(rot0[0] @ turn)], q0,
                    np.r_[on_tool / 1e3, 0.0, 0.0, 0.0], tol_m=1e-13)
        if q is not None:
            q = design.nearest_turn(q, q0, model.joint_limits)
            if np.all(q >= model.joint_limits[:, 0]) and np.all(q <= model.joint_limits[:, 1]):
                qs.append(q)
    return model, np.array(qs), tool, stylus[0] * 1e3


SEED_DH = tuple(f"{p}{i}" for i in range(2, 7) for p in ("theta", "d", "a", "alpha"))  # links 2-6


def null_terms(word: str) -> dict[str, float]:
    """One of rank_report's null directions ("- theta6 + tool.rz + 0.25*tool.y") as {name: coefficient}.
    A null vector's sign, and which of two equal columns the pivoted QR calls dependent, are
    arbitrary (they differ between BLAS kernels), so the checks below compare up to sign."""
    tokens = (word if word.startswith("- ") else "+ " + word).split()
    out = {}
    for sign, term in zip(tokens[::2], tokens[1::2]):
        coef, _, name = term.rpartition("*")
        out[name] = (-1.0 if sign == "-" else 1.0) * (float(coef) if coef else 1.0)
    return out


def up_to_sign(terms: dict, want: dict, tol: float = 0.005) -> bool:
    """The same direction as `want`, either sign; tol: half the words' last printed digit."""
    return terms.keys() == want.keys() and any(all(abs(s * terms[k] - v) <= tol for k, v in want.items())
                                               for s in (1.0, -1.0))


@pytest.mark.parametrize("where, rank", [("spread", 22), ("generatrix", 17), ("point", 16)])
def test_one_stylus_cannot_identify_the_seeds_29_parameters(where, rank):
    """The seed fits 20 DH errors (links 2-6), 6 tool and 3 stylus parameters to contacts on
    one stylus. The rank of that model's Jacobian is 22 at most, however many contacts: link
    6 moves with the tool (d6, a6, alpha6, theta6), the cylinder hides the tool's slide along
    and turn about its axis, and the parallel joints 2 and 3 see only d2 - d3. Contacts all on
    one generatrix lose 5 more (the tool's sideways shift with a5 and d5, its turn about the
    radius, and a trade of arm lengths against the stylus); all at one point of the tool, as
    in the seed's simulation, 6 more."""
    model, q, tool, stylus = puma_contacts(where)
    report = design.rank_report(model, q, tool, [0.0, 0.0, -20.0], [1.0, 0.0, 0.0], stylus, SEED_DH)
    assert report["parameters"] == 29 and report["rank"] == rank, report
    hidden = report["not_identifiable"]
    dirs = [null_terms(w) for w in hidden]  # compared up to sign: see null_terms
    assert "tool.x" in hidden and "a6" in hidden and any(up_to_sign(d, {"d2": 1.0, "d3": -1.0}) for d in dirs), hidden
    assert any(abs(abs(d.get("theta6", 0.0)) - 1.0) < 0.005 for d in dirs), hidden  # theta6 at full weight, either sign
    if where != "spread":
        # stylus.x with a2 at 0.68 of its weight, the same sign (a2 and d4 tie at 0.68: their order is arbitrary)
        assert {"tool.y", "a5", "d5"} <= set(hidden) and any(
            abs(abs(d.get("stylus.x", 0.0)) - 1.0) < 0.005 and abs(d.get("a2", 0.0) / d["stylus.x"] - 0.68) < 0.005
            for d in dirs), hidden
    more = design.rank_report(model, puma_contacts(where, 80, seed=1)[1], tool, [0.0, 0.0, -20.0],
                              [1.0, 0.0, 0.0], stylus, SEED_DH)
    assert more["rank"] == rank  # more contacts do not help


def test_the_run_report_draws_the_contacts_on_the_fitted_cylinder(default_run, tmp_path):
    _, result, *_ = default_run
    assert_report_draws(result, tmp_path, "across the tool axis", "along the tool axis")
    side = layer(result, "across the tool axis", "side contacts")
    radius = result.extra["contact_radius_mm"]
    off = np.linalg.norm(side, axis=1) - radius  # the ball's centre off the fitted cylinder, per kept side contact
    assert len(side) >= 20 and np.abs(off).max() < 5 * 0.02
