"""Every fit in solvers ends in the same words: status, message, success and nfev as
scipy.optimize.OptimizeResult has them, covariance where the fit has one (solvers.estimation.fit_result).
A fit that converged says success; one its data leave undetermined says not, and why."""
from __future__ import annotations

import dataclasses
import importlib
import inspect
import pkgutil

import numpy as np
import pytest
from scipy.optimize import brentq

import cellcal.solvers
from cellcal.config.robot_files import load_robot
from cellcal.sims.physics.kinematic_arm import SimulatedArm
from cellcal.sims.physics.workspace import full_workspace
from cellcal.solvers.tool_frames import handshake as hs
from cellcal.solvers.estimation import lsq
from cellcal.solvers.tool_frames import pivot as pv
from cellcal.solvers.geometry import se3
from cellcal.solvers.tool_frames import stylus as fitting
from cellcal.solvers.tool_frames import tcp_laser as laser
from cellcal.solvers.analysis.effects import Term
from cellcal.solvers.analysis.extended_model import ExtendedFit, fit_extended
from cellcal.solvers.estimation.fit_result import FitResult, degenerate, from_solver, solved
from cellcal.solvers.identification.identify import Identification, IdentifyOptions, fit, identify
from cellcal.solvers.identification.kinematic_fit import Fit

COMMON = {"status": int, "message": str, "success": bool, "nfev": int}
FIT_CLASSES = (laser.LaserFit, hs.HandshakeFit, pv.PivotFit, pv.AxisFit, fitting.StylusFit, Fit, ExtendedFit,
               Identification)


def solver_classes():
    """Every class defined in a solvers module whose name ends in Fit."""
    for info in pkgutil.walk_packages(cellcal.solvers.__path__, "cellcal.solvers."):
        module = importlib.import_module(info.name)
        for name, cls in inspect.getmembers(module, inspect.isclass):
            if cls.__module__ == module.__name__ and name.endswith("Fit"):
                yield cls


def check(result, success: bool) -> None:
    """The common fields, typed as scipy has them, and consistent with one another."""
    for name, kind in COMMON.items():
        assert isinstance(getattr(result, name), kind), (type(result).__name__, name)
    assert result.success is success, result.message
    assert (result.status > 0) == success and result.message and result.nfev >= 0
    assert result.covariance is None or np.all(np.isfinite(np.diag(result.covariance))) or not success


def test_every_fit_class_in_solvers_carries_the_common_fields():
    found = set(solver_classes())
    assert found >= set(FIT_CLASSES) - {Identification}, found
    for cls in found | set(FIT_CLASSES):
        assert issubclass(cls, FitResult), cls
        names = {f.name for f in dataclasses.fields(cls)}
        assert {"status", "message", "success", "nfev", "covariance"} <= names, cls
        assert not hasattr(cls, "converged"), cls
    assert all("residuals_mm" in {f.name for f in dataclasses.fields(cls)} for cls in FIT_CLASSES)


def test_a_solver_that_ran_out_of_evaluations_or_was_given_bad_input_is_no_success():
    for status, success in ((-1, False), (0, False), (1, True), (4, True)):
        ended = from_solver(lsq.Solution(np.zeros(1), 0.0, 7, 7, status, "why"))
        assert ended == {"status": status, "message": "why", "success": success, "nfev": 7}
    assert solved("the tip")["success"] and solved("the tip")["status"] == 1
    assert not degenerate("no spread")["success"] and degenerate("no spread")["status"] < 0


# -- closed form: the pivot and the tool axis ------------------------------------------------------

def pivot_seats(rotations):
    t, c = np.array([0.4, -0.3, 150.0]), np.array([-700.0, 50.0, 400.0])
    return rotations, c - np.einsum("nij,j->ni", rotations, t)


def test_a_pivot_over_turned_seats_is_solved_and_one_turned_about_one_axis_is_not():
    rotations = se3.rotvec_to_matrix(np.random.default_rng(0).normal(0.0, 0.4, (8, 3)))
    result = pv.fit_pivot(*pivot_seats(rotations), noise_floor=0.01)
    check(result, True)
    assert result.status == 1 and result.nfev == 0 and "8 of 8 seats" in result.message
    assert result.covariance.shape == (6, 6) and result.residuals_mm.shape == (8, 3)
    about_z = np.array([se3.rot("z", a) for a in np.linspace(0.0, 2.0, 8)])
    flat = pv.fit_pivot(*pivot_seats(about_z), noise_floor=0.01)
    check(flat, False)
    assert "do not determine the tip centre" in flat.message


def crossing_rows(heights):
    down = np.diag([1.0, -1.0, -1.0])
    line, rotations, directions, h = [], [], [], []
    for j in range(3):
        for height in heights:
            for k, e in enumerate(np.eye(3)[:2]):
                line.append(2 * j + k)
                rotations.append(se3.rot("z", 2 * np.pi * j / 3) @ down)
                directions.append(e)
                h.append(height)
    line, rotations, directions, h = map(np.array, (line, rotations, directions, h))
    axis = np.array([0.01, 0.005, 1.0]) / np.linalg.norm([0.01, 0.005, 1.0])
    crossing = [-550.0, -400.0, 400.0] - rotations @ [0.4, -0.3, 150.0] + h[:, None] * (rotations @ axis)
    return line, rotations, directions, h, np.einsum("ni,ni->n", directions, crossing)


def test_an_axis_from_two_heights_is_solved_and_from_one_height_it_is_not():
    line, rotations, directions, heights, midpoints = crossing_rows((15.0, 85.0))
    result = pv.fit_axis(line, rotations, directions, heights, midpoints, [0.0, 0.0, 1.0])
    check(result, True)
    assert result.status == 1 and result.nfev == 0 and result.covariance.shape == (8, 8)
    line, rotations, directions, heights, midpoints = crossing_rows((50.0, 50.0))
    flat = pv.fit_axis(line, rotations, directions, heights, midpoints, [0.0, 0.0, 1.0])
    check(flat, False)
    assert "do not determine the axis' tilt" in flat.message


# -- least squares ---------------------------------------------------------------------------------

def test_the_handshake_reports_least_squares_own_ending():
    rng = np.random.default_rng(1)
    points = rng.uniform(-200, 200, (8, 3)) + [-900.0, 0.0, 550.0]
    rotation, translation = se3.rotvec_to_matrix([0.004, -0.002, np.pi - 0.003]), np.array([-1800.0, 2.0, 3.0])
    tip_a, tip_b = np.array([0.5, -0.3, 150.4]), np.array([-0.2, 0.7, 149.5])
    ra, rb = (se3.rotvec_to_matrix(rng.normal(0.0, 0.3, (8, 3))) for _ in range(2))
    pa = points - np.einsum("nij,j->ni", ra, tip_a)
    pb = (points - translation) @ rotation - np.einsum("nij,j->ni", rb, tip_b)
    result = hs.fit_handshake(ra, pa, rb, pb, [0.0, 0.0, 150.0], [0.0, 0.0, 150.0])
    check(result, True)
    assert result.nfev > 0 and result.covariance.shape == (12, 12)
    flat = points.copy()
    flat[:, 2] = 550.0
    pa = flat - np.einsum("nij,j->ni", ra, tip_a)
    with pytest.raises(hs.HandshakeRefused, match="lie on one plane"):  # refused, never a result
        hs.fit_handshake(ra, pa, rb, pb, [0.0, 0.0, 150.0], [0.0, 0.0, 150.0])


def test_the_stylus_fit_reports_its_last_solve_and_every_evaluation():
    rng = np.random.default_rng(0)
    u = np.array([0.01, -0.02, 1.0]) / np.linalg.norm([0.01, -0.02, 1.0])
    tip, stylus, r_s, radius = np.array([0.4, -0.3, 150.2]), np.array([-550.0, -400.0, 400.0]), 0.5, 3.5
    e1 = np.cross(u, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    n, faces = 60, 6
    rot = se3.rotvec_to_matrix(rng.normal(size=(n + faces, 3)) * 0.6)
    phi, h = rng.uniform(-np.pi, np.pi, n + faces), rng.uniform(8, 90, n + faces)
    point = tip - h[:, None] * u + radius * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    point[n:] = tip + r_s * u
    contacts = fitting.Contacts(rot, stylus - np.einsum("nij,nj->ni", rot, point), np.r_[np.zeros(n, int),
                                                                                         np.ones(faces, int)])
    start = fitting.Line(tip + [0.8, -0.5, 0.3], np.array([0.0, 0.0, 1.0]))
    result = fitting.fit(contacts, fitting.Setup(start, r_s, 3.0, True, "round"), stylus + [1, -1, 0.5])
    check(result, True)
    assert result.nfev > 1 and result.covariance.shape == (len(result.names),) * 2
    np.testing.assert_allclose(result.tip_mm, tip, atol=1e-7)


def laser_edges(geometry, latency_s):
    """Edges of sweeps there and back across every beam, the tool tilted and turned round, at two
    heights up the tool."""
    model = laser._Model(laser.LaserEdges(np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 3)),
                                          np.zeros(0, int), np.zeros(0, int)), geometry)
    rows, move = [], 0
    for yaw, tilt in ((0.0, 0.0), (0.0, 0.3), (np.pi / 2, 0.3), (np.pi, 0.3), (-np.pi / 2, 0.3)):
        rotation = se3.rot("z", yaw) @ se3.rot("x", tilt) @ np.diag([1.0, -1.0, -1.0])
        for height in (20.0, 40.0):
            for way in (1.0, -1.0):
                velocity = way * np.array([40.0, 40.0, 0.0])
                start = np.array([0.0, 0.0, 150.0 - height]) - 5.0 * velocity  # the beams `height` up the tool
                for beam in range(len(geometry.beam_points_mm)):
                    def gap(s, beam=beam):
                        flange = (start + s * velocity)[None]
                        edges = laser.LaserEdges(rotation[None], flange, velocity[None], np.array([beam]),
                                                 np.array([move]))
                        model.edges = edges
                        return model.residuals(model.start())[0]
                    s = np.linspace(0.0, 10.0, 401)
                    g = np.array([gap(v) for v in s])
                    for i in np.flatnonzero(np.sign(g[1:]) != np.sign(g[:-1])):
                        at = brentq(gap, s[i], s[i + 1], xtol=1e-13)
                        rows.append((rotation, start + (at + latency_s) * velocity, velocity, beam, move))
                move += 1
    rotation, flange, velocity, beam, move = map(np.array, zip(*rows))
    return laser.LaserEdges(rotation, flange, velocity, beam, move)


def test_the_laser_fit_reports_least_squares_own_ending():
    geometry = laser.LaserGeometry(3.0, 60.0, np.array([0.0, 0.0, 150.0]), np.array([0.0, 0.0, 1.0]),
                                   np.zeros((2, 3)), np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
                                   np.array([3.5, 3.5]))
    edges = laser_edges(geometry, 0.002)
    result = laser.fit(edges, geometry, 0.01, 1e-4)
    check(result, True)
    assert result.nfev > 0 and result.covariance.shape == (len(result.names),) * 2
    assert abs(result.latency_s - 0.002) < 1e-6, result.latency_s


# -- the kinematic fits ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def campaign():
    model = load_robot("abb-irb4600")
    rng = np.random.default_rng(7)
    arm = SimulatedArm(model, rng)
    return model, arm.measure(full_workspace(model, 60, rng))


def test_identification_and_the_fits_under_it_report_how_they_ended(campaign):
    model, cal = campaign
    result = identify(model, cal, IdentifyOptions(regularize="none"))
    check(result, True)
    n = result.layout.size
    assert result.covariance.shape == (n, n)
    np.testing.assert_allclose(np.sqrt(np.diag(result.covariance)), result.std, rtol=1e-12, atol=0.0)
    refit = fit(result.layout, cal, result.x_nominal, result.free)
    check(refit, True)
    assert refit.nfev > 0 and refit.covariance is None
    # geometry and a term together: a made-up displacement along x growing with joint 2
    term = Term("made_up", {}, ("dx",), cart_basis=np.sin(cal.q[:, 1])[:, None, None] * [[1.0], [0.0], [0.0]])
    extended = fit_extended(result.layout, cal, result.x, result.free, (term,), prior_mm=1.0)
    check(extended, True)
    assert extended.nfev > 0 and extended.residuals_mm.shape == (60, 3)
