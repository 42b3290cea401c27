"""Our forward kinematics against an independent implementation (Corke's Robotics Toolbox).

Each reference robot is rebuilt as a cellcal model *from the toolbox robot's own
link parameters* (a, alpha, d, offset; metres and radians), so what is checked is
the DH / MDH convention and the unit handling of the loader, not numbers copied by
hand. The toolbox's base and tool transforms are composed around our flange frame:
    T_rtb(q) = base @ T_ours(q) @ tool.
Tolerances: 1e-9 m on the flange position, 1e-9 on every rotation-matrix entry.
"""
import math

import numpy as np
import pytest
import yaml

rtb = pytest.importorskip("roboticstoolbox")

from cellcal.config.robot_files import load_robot, shipped_robots  # noqa: E402
from cellcal.solvers.geometry.chain import forward  # noqa: E402
from cellcal.config.robot_files import model_from_mapping  # noqa: E402

N_CONFIGS = 50
POS_TOL_M = 1e-9
ROT_TOL = 1e-9

# Classic DH: Puma560, UR5, UR10 (required), IRB140 (plain 6R), Jaco (non-zero theta
# offsets, 60 deg twists, and flipped joints, compared at negated joint values).
# Modified DH: Panda (7 joints, tool transform), AL5D (MDH with non-zero theta offsets
# and a tool transform).
DH_REFERENCES = ["Puma560", "UR5", "UR10", "IRB140", "Jaco"]
MDH_REFERENCES = ["Panda", "AL5D"]


def rtb_robot(name):
    return getattr(rtb.models.DH, name)()


def mapping_from_rtb(robot) -> dict:
    """A cellcal model mapping written from the toolbox robot's link parameters."""
    rows = []
    for link in robot.links:
        assert link.isrevolute, f"{robot.name}: only revolute joints are modelled"
        rows.append({"a": float(link.a), "alpha": float(link.alpha), "d": float(link.d),
                     "theta": float(link.offset)})
    return {
        "name": f"rtb-{robot.name}",
        "convention": "mdh" if robot.mdh else "dh",
        "length_unit": "m",
        "angle_unit": "rad",
        "joints": rows,
    }


def joint_signs(robot) -> np.ndarray:
    """-1 for the toolbox's flipped joints (theta = offset - q): our file format has no joint direction,
    so such a joint is compared at the negated joint value."""
    return np.array([-1.0 if getattr(link, "isflip", False) else 1.0 for link in robot.links])


def random_configs(n_joints, seed):
    # well beyond +/- pi so wrap-around and large angles are exercised too
    return np.random.default_rng(seed).uniform(-2 * math.pi, 2 * math.pi, (N_CONFIGS, n_joints))


def rtb_fkine(robot, q) -> np.ndarray:
    """(N, 4, 4) toolbox flange(+tool) poses, metres."""
    return np.array([np.asarray(robot.fkine(qi).A) for qi in q])


def ours_homogeneous(model, params, q) -> np.ndarray:
    """(N, 4, 4) our flange poses, converted to metres."""
    rot, org = forward(model.chains["flange"], params, q)
    out = np.zeros((len(q), 4, 4))
    out[:, :3, :3] = rot
    out[:, :3, 3] = org / 1000.0
    out[:, 3, 3] = 1.0
    return out


def assert_same_poses(expected, actual, label):
    pos_err = np.abs(expected[:, :3, 3] - actual[:, :3, 3]).max()
    rot_err = np.abs(expected[:, :3, :3] - actual[:, :3, :3]).max()
    assert pos_err <= POS_TOL_M, f"{label}: position differs by {pos_err:.3e} m"
    assert rot_err <= ROT_TOL, f"{label}: rotation entry differs by {rot_err:.3e}"


@pytest.mark.parametrize("name", DH_REFERENCES + MDH_REFERENCES)
def test_forward_kinematics_matches_rtb(name):
    robot = rtb_robot(name)
    model = model_from_mapping(mapping_from_rtb(robot), source=f"rtb:{name}")
    assert model.convention == ("mdh" if robot.mdh else "dh")
    q = random_configs(robot.n, seed=sum(map(ord, name)))
    base = np.asarray(robot.base.A)
    tool = np.asarray(robot.tool.A)
    expected = rtb_fkine(robot, q)
    ours = base @ ours_homogeneous(model, model.nominal, q * joint_signs(robot)) @ tool
    assert_same_poses(expected, ours, name)


def test_reference_set_covers_both_conventions_and_offsets():
    """The comparison above is only meaningful if it exercises MDH and theta offsets."""
    robots = {n: rtb_robot(n) for n in DH_REFERENCES + MDH_REFERENCES}
    assert all(not robots[n].mdh for n in DH_REFERENCES)
    assert all(robots[n].mdh for n in MDH_REFERENCES)
    assert any(link.offset != 0 for n in DH_REFERENCES for link in robots[n].links)
    assert any(link.offset != 0 for n in MDH_REFERENCES for link in robots[n].links)
    assert any(not np.allclose(robots[n].tool.A, np.eye(4)) for n in MDH_REFERENCES)
    for n in ("Puma560", "UR5", "UR10", "Panda"):
        assert (joint_signs(robots[n]) == 1).all(), f"{n} has flipped joints"


# --- the shipped model files -----------------------------------------------------------

def rtb_from_file(path):
    """A toolbox robot built from a shipped YAML file's raw rows, converted here, not by cellcal."""
    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    lu = {"mm": 1e-3, "m": 1.0}[doc["length_unit"]]
    au = {"deg": math.pi / 180.0, "rad": 1.0}[doc["angle_unit"]]
    assert doc.get("joint_coupling", "none") == "none"
    links = []
    for row in doc["joints"]:
        # the toolbox has no Hayati beta; only files whose betas are all zero can be compared
        assert row.get("beta", 0) == 0
        cls = rtb.RevoluteMDH if doc["convention"] == "mdh" else rtb.RevoluteDH
        links.append(cls(a=row["a"] * lu, alpha=row["alpha"] * au, d=row["d"] * lu, offset=row["theta"] * au))
    return rtb.DHRobot(links, name=doc["name"])


@pytest.mark.parametrize("name", sorted(n for n in shipped_robots() if n != "agile-justin"))  # serial arms
def test_shipped_file_matches_rtb_built_from_the_same_rows(name):
    """Our loader (units, convention, beta = 0) and FK agree with the toolbox on every shipped file."""
    path = shipped_robots()[name]
    robot = rtb_from_file(path)
    model = load_robot(name)
    q = random_configs(model.n_joints, seed=7)
    assert_same_poses(rtb_fkine(robot, q), ours_homogeneous(model, model.nominal, q), name)


def test_shipped_puma560_is_rtb_puma560_with_base_at_shoulder_height():
    """config/robots/puma560.yaml is the toolbox's Puma560 except d1: ours puts the base frame at
    the shoulder (d1 = 0), the toolbox 0.67183 m lower at the mounting surface."""
    robot = rtb_robot("Puma560")
    model = load_robot("puma560")
    d1 = robot.links[0].d
    assert d1 == pytest.approx(0.67183, abs=1e-9)
    q = random_configs(6, seed=560)
    lift = np.eye(4)
    lift[2, 3] = d1
    assert_same_poses(rtb_fkine(robot, q), lift @ ours_homogeneous(model, model.nominal, q), "puma560.yaml")


@pytest.mark.parametrize("ours, classic", [("ur5e", "UR5"), ("ur10e", "UR10")])
def test_shipped_ur_e_series_has_the_classic_ur_link_structure(ours, classic):
    """The shipped e-Series file uses the same link structure as the toolbox's classic UR model (twists,
    theta offsets, signs of a and d), i.e. the same base frame, zero pose and joint directions; only the
    lengths differ between the series."""
    model = load_robot(ours)
    robot = rtb_robot(classic)
    for j, link in enumerate(robot.links, start=1):
        assert model.nominal[model.index(f"alpha{j}")] == pytest.approx(link.alpha, abs=1e-12)
        assert model.nominal[model.index(f"theta{j}")] == pytest.approx(link.offset, abs=1e-12)
        assert np.sign(model.nominal[model.index(f"a{j}")]) == np.sign(link.a)
        assert np.sign(model.nominal[model.index(f"d{j}")]) == np.sign(link.d)


@pytest.mark.parametrize("ours, rtb_name", [("ur5e", "UR5e"), ("ur10e", "UR10e")])
def test_shipped_ur_e_series_matches_rtb_e_series(ours, rtb_name):
    """FK of the shipped e-Series file equals the toolbox's e-Series model, where the toolbox has one."""
    cls = getattr(rtb.models.DH, rtb_name, None)
    if cls is None:
        pytest.skip(f"roboticstoolbox {rtb.__version__} has no models.DH.{rtb_name}")
    robot = cls()
    model = load_robot(ours)
    q = random_configs(6, seed=5)
    expected = rtb_fkine(robot, q)
    ours_t = np.asarray(robot.base.A) @ ours_homogeneous(model, model.nominal, q) @ np.asarray(robot.tool.A)
    assert_same_poses(expected, ours_t, ours)


# --- the makers' models against the toolbox's own models of the same robots ----------------------

def test_shipped_ur10_is_rtb_ur10():
    """config/robots/ur10.yaml (UR's CB3 table) and the toolbox's UR10 are the same robot, to rounding."""
    robot = rtb_robot("UR10")
    model = load_robot("ur10")
    q = random_configs(6, seed=10)
    assert_same_poses(rtb_fkine(robot, q), ours_homogeneous(model, model.nominal, q), "ur10.yaml")


def test_shipped_ur5_is_rtb_ur5_but_for_the_toolboxs_d1():
    """config/robots/ur5.yaml has UR's d1 = 0.089159 m; the toolbox's UR5 has 0.089459 m, 0.3 mm more (every
    other row is UR's). d1 is a Tz right after Rz(q1), so the toolbox's UR5 is ours lifted 0.3 mm along the
    base z: compared as such, everything else must agree to rounding."""
    robot = rtb_robot("UR5")
    model = load_robot("ur5")
    lift_m = robot.links[0].d - model.nominal[model.index("d1")] / 1000.0
    assert lift_m == pytest.approx(0.0003, abs=1e-12)  # the one known difference, and no other value of it
    lift = np.eye(4)
    lift[2, 3] = lift_m
    q = random_configs(6, seed=5)
    assert_same_poses(rtb_fkine(robot, q), lift @ ours_homogeneous(model, model.nominal, q), "ur5.yaml")


def test_shipped_franka_panda_is_rtb_panda_without_its_hand():
    """config/robots/franka-panda.yaml is Franka's table with the flange row folded into d7; the toolbox's
    Panda has the same rows (d7 = 0.107 m too) and adds the hand as its tool (Tz(0.103 m) Rz(-45 deg)), which
    is not part of a nominal arm file (every calibration estimates the target offset): ours @ tool = toolbox."""
    robot = rtb_robot("Panda")
    model = load_robot("franka-panda")
    tool = np.asarray(robot.tool.A)
    assert tool[2, 3] == pytest.approx(0.103, abs=1e-12)  # the hand, as described above
    q = random_configs(7, seed=7)
    assert_same_poses(rtb_fkine(robot, q), ours_homogeneous(model, model.nominal, q) @ tool, "franka-panda.yaml")
    limits = np.array([link.qlim for link in robot.links])
    np.testing.assert_allclose(model.joint_limits, limits, rtol=0, atol=1e-8)  # Franka's limits, written in deg to 1e-8 rad


# The iiwa 14 R820 URDF shipped with the toolbox's data (ROS-Industrial's kuka_experimental): its joint origins
# put A2 0.43624 mm off the arm's line in -x and A4 as much back in +x (a modelling offset of that description;
# KUKA's drawing has all axes on one line). Each is a translation in a frame, so neither changes a rotation,
# and each moves the flange by at most its own length: the positions must agree within the sum.
IIWA_URDF_OFFSET_M = 2 * 0.00043624


def test_shipped_kuka_iiwa14_matches_the_urdf_description():
    """config/robots/kuka-iiwa14.yaml (KUKA's dimensions as classic DH) against the URDF of the same arm:
    same joint axes and senses (rotations to 1e-9), same lengths (positions within the URDF's two offsets)."""
    urdf = getattr(rtb.models.URDF, "LBR", None)
    if urdf is None:
        pytest.skip(f"roboticstoolbox {rtb.__version__} has no models.URDF.LBR")
    robot = urdf()
    assert robot.n == 7
    model = load_robot("kuka-iiwa14")
    q = random_configs(7, seed=14)
    expected = np.array([np.asarray(robot.fkine(qi, end="tool0").A) for qi in q])
    ours = ours_homogeneous(model, model.nominal, q)
    rot_err = np.abs(expected[:, :3, :3] - ours[:, :3, :3]).max()
    assert rot_err <= ROT_TOL, f"kuka-iiwa14.yaml: rotation entry differs by {rot_err:.3e}"
    pos_err = np.linalg.norm(expected[:, :3, 3] - ours[:, :3, 3], axis=1).max()
    assert pos_err <= IIWA_URDF_OFFSET_M + POS_TOL_M, f"kuka-iiwa14.yaml: position differs by {pos_err:.3e} m"
    # and the offsets are all there is: at A2 = A3 = 0 they cancel (both along the same x), so there it is exact
    q0 = q.copy()
    q0[:, 1] = 0.0
    q0[:, 2] = 0.0
    expected0 = np.array([np.asarray(robot.fkine(qi, end="tool0").A) for qi in q0])
    assert_same_poses(expected0, ours_homogeneous(model, model.nominal, q0), "kuka-iiwa14.yaml at A2 = A3 = 0")
    # The URDF's ranges are KUKA's, written in rad a little inside (2.9668 for 170 deg = 2.96706 rad, 3.0541 for 175 deg):
    # each lies inside ours by less than 0.03 deg (5e-4 rad), far below any difference between two robot variants (>= 5 deg).
    urdf_limits = np.array(robot.qlim).T
    inside = np.concatenate([urdf_limits[:, 0] - model.joint_limits[:, 0], model.joint_limits[:, 1] - urdf_limits[:, 1]])
    assert np.all((inside >= 0) & (inside < 5e-4)), inside
