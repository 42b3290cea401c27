"""Robot model files: the shipped models, their reference poses, joint coupling, and bad files.

Every refusal must be a ModelError whose message names the file and the offending key
(or, for YAML syntax errors, the file and the line), so a user can fix the file.
"""
import math

import numpy as np
import pytest

from cellcal.config.robot_files import load_robot, shipped_robots
from cellcal.solvers.geometry.chain import forward
from cellcal.config.robot_files import ModelError, model_from_mapping

REQUIRED_SHIPPED = {"ur5e", "ur10e", "abb-irb4600", "elite-ec66", "puma560", "epson-c4-a901s"}


def flange(model, q):
    rot, org = forward(model.chains["flange"], model.nominal, np.atleast_2d(q))
    return rot[0], org[0]


# --- shipped models ------------------------------------------------------------------

def test_the_required_models_ship():
    assert REQUIRED_SHIPPED <= set(shipped_robots())


SERIAL = sorted(n for n in shipped_robots() if n != "agile-justin")  # the tree has tests of its own


@pytest.mark.parametrize("name", SERIAL)
def test_shipped_model_loads(name):
    """Loads by name and by path to the same model; 6 or 7 joints, finite nominal values, limits below their
    highs, orthonormal flange frames."""
    model = load_robot(name)
    by_path = load_robot(shipped_robots()[name])
    np.testing.assert_array_equal(model.nominal, by_path.nominal)
    assert model.param_names == by_path.param_names
    n = model.n_joints
    assert n in (6, 7)  # the shipped serial arms: 6R industrial arms and 7R (redundant) cobots
    assert model.convention in ("dh", "mdh")
    assert np.all(np.isfinite(model.nominal))
    assert len(model.param_names) == len(model.nominal) == len(model.param_is_angle)
    if model.joint_limits is not None:
        assert model.joint_limits.shape == (n, 2)
        assert np.all(model.joint_limits[:, 0] < model.joint_limits[:, 1])
        # limits are converted to rad: no arm turns a joint more than 2 turns either way
        assert np.all(np.abs(model.joint_limits) <= 4 * math.pi + 1e-9)
    q = np.random.default_rng(0).uniform(-np.pi, np.pi, (20, n))
    rot, _ = forward(model.chains["flange"], model.nominal, q)
    np.testing.assert_allclose(rot @ np.swapaxes(rot, 1, 2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)


@pytest.mark.parametrize("name, expected_mm", [
    ("ur5e", (-817.2, -232.9, 62.8)),        # UR classic DH zero pose: x = a2 + a3, y = -(d4 + d6), z = d1 - d5
    ("ur10e", (-1184.25, -290.7, 60.85)),
    ("abb-irb4600", (1580.0, 0.0, 1765.0)),  # ABB home position of the IRB 4600-40/2.55
    ("epson-c4-a901s", (0.0, 565.0, 720.0)),  # Yan et al. (Sensors 2025): fkine at q = 0 from their Table 6
    ("puma560", (452.1, -150.05, 431.8)),    # Corke's qz pose, base frame at shoulder height
    ("elite-ec66", (816.0, 33.0, -2.0)),      # Elite URDF zero pose (per the file's own note)
    ("ur5", (-817.25, -191.45, -5.491)),     # CB3: x = a2 + a3, y = -(d4 + d6), z = d1 - d5 as for the e-Series
    ("ur10", (-1184.3, -256.141, 11.6)),
    ("franka-panda", (88.0, 0.0, 926.0)),    # x = a7, z = d1 + d3 + d5 - d7 (a4 and a5 cancel; the flange points down)
    ("kuka-iiwa14", (0.0, 0.0, 1306.0)),     # KUKA's upright arm: 360 + 420 + 400 + 126
])
def test_flange_position_at_zero_joints(name, expected_mm):
    """Flange origin at all-zero joints within 0.1 mm."""
    model = load_robot(name)
    _, org = flange(model, np.zeros(model.n_joints))
    np.testing.assert_allclose(org, expected_mm, rtol=0, atol=0.1)


@pytest.mark.parametrize("name, z_axis", [
    ("ur5e", (0, -1, 0)), ("ur10e", (0, -1, 0)), ("abb-irb4600", (1, 0, 0)),
    ("epson-c4-a901s", (0, -1, 0)), ("puma560", (0, 0, 1)), ("elite-ec66", (0, -1, 0)),
    ("ur5", (0, -1, 0)), ("ur10", (0, -1, 0)), ("franka-panda", (0, 0, -1)), ("kuka-iiwa14", (0, 0, 1)),
])
def test_flange_z_axis_at_zero_joints(name, z_axis):
    """Flange approach direction at all-zero joints, as each file documents it (1e-12)."""
    model = load_robot(name)
    rot, _ = flange(model, np.zeros(model.n_joints))
    np.testing.assert_allclose(rot[:, 2], z_axis, rtol=0, atol=1e-12)


def test_units_are_converted_to_mm_and_rad():
    """ur5e.yaml gives mm/deg; the compiled nominal values are mm/rad."""
    model = load_robot("ur5e")
    assert model.nominal[model.index("d1")] == pytest.approx(162.5, abs=1e-12)
    assert model.nominal[model.index("a2")] == pytest.approx(-425.0, abs=1e-12)
    assert model.nominal[model.index("alpha1")] == pytest.approx(math.pi / 2, abs=1e-15)
    np.testing.assert_allclose(model.joint_limits, np.tile([-2 * math.pi, 2 * math.pi], (6, 1)), atol=1e-12)
    # the same arm written in m/rad compiles to the same numbers
    metric = {
        "name": "ur5e-m", "convention": "dh", "length_unit": "m", "angle_unit": "rad",
        "joints": [
            {"a": 0, "alpha": math.pi / 2, "d": 0.1625, "theta": 0},
            {"a": -0.425, "alpha": 0, "d": 0, "theta": 0},
            {"a": -0.3922, "alpha": 0, "d": 0, "theta": 0},
            {"a": 0, "alpha": math.pi / 2, "d": 0.1333, "theta": 0},
            {"a": 0, "alpha": -math.pi / 2, "d": 0.0997, "theta": 0},
            {"a": 0, "alpha": 0, "d": 0.0996, "theta": 0},
        ],
    }
    np.testing.assert_allclose(model_from_mapping(metric).nominal, model.nominal, rtol=0, atol=1e-9)


def test_epson_betas_are_parameters():
    """An MDH file with beta keys gets beta1..beta6 in its parameter vector (5 parameters per joint)."""
    model = load_robot("epson-c4-a901s")
    assert model.n_params == 30
    assert all(f"beta{j}" in model.param_names for j in range(1, 7))
    assert "beta1" not in load_robot("elite-ec66").param_names


# --- joint coupling ------------------------------------------------------------------

def abb_mapping(**extra):
    doc = {
        "name": "abb-like", "convention": "dh", "length_unit": "mm", "angle_unit": "deg",
        "joints": [
            {"a": 175, "alpha": -90, "d": 495, "theta": 0},
            {"a": 1095, "alpha": 0, "d": 0, "theta": -90},
            {"a": 175, "alpha": -90, "d": 0, "theta": 0},
            {"a": 0, "alpha": 90, "d": 1270, "theta": 0},
            {"a": 0, "alpha": -90, "d": 0, "theta": 0},
            {"a": 0, "alpha": 0, "d": 135, "theta": 0},
        ],
    }
    doc.update(extra)
    return doc


@pytest.mark.parametrize("convention", ["dh", "mdh"])
def test_fanuc_j2_j3_coupling_is_q3_plus_q2(convention):
    """FK(q) with fanuc_j2_j3 equals FK of the uncoupled model at q' with q'3 = q3 + q2 (50 random q;
    1e-9 mm, 1e-12 in rotation entries); and the coupling actually changes the pose."""
    coupled = model_from_mapping(abb_mapping(convention=convention, joint_coupling="fanuc_j2_j3"))
    plain = model_from_mapping(abb_mapping(convention=convention))
    assert coupled.param_names == plain.param_names
    q = np.random.default_rng(1).uniform(-np.pi, np.pi, (50, 6))
    q_plain = q.copy()
    q_plain[:, 2] = q[:, 2] + q[:, 1]
    r_c, o_c = forward(coupled.chains["flange"], coupled.nominal, q)
    r_p, o_p = forward(plain.chains["flange"], plain.nominal, q_plain)
    np.testing.assert_allclose(o_c, o_p, rtol=0, atol=1e-9)
    np.testing.assert_allclose(r_c, r_p, rtol=0, atol=1e-12)
    _, o_same_q = forward(plain.chains["flange"], plain.nominal, q)
    assert np.abs(o_c - o_same_q).max() > 100.0


def test_coupling_none_is_the_default():
    a = model_from_mapping(abb_mapping())
    b = model_from_mapping(abb_mapping(joint_coupling="none"))
    q = np.random.default_rng(2).uniform(-np.pi, np.pi, (10, 6))
    np.testing.assert_array_equal(forward(a.chains["flange"], a.nominal, q)[1],
                                  forward(b.chains["flange"], b.nominal, q)[1])


# --- bad files -----------------------------------------------------------------------

GOOD = """\
name: test-arm
convention: {convention}
length_unit: mm
angle_unit: deg
joints:
  - {{a: 175,  alpha: -90, d: 495,  theta: 0}}
  - {{a: 1095, alpha: 0,   d: 0,    theta: -90}}
  - {{a: 175,  alpha: -90, d: 0,    theta: 0}}
  - {{a: 0,    alpha: 90,  d: 1270, theta: 0}}
  - {{a: 0,    alpha: -90, d: 0,    theta: 0}}
  - {{a: 0,    alpha: 0,   d: 135,  theta: 0}}
joint_limits: [[-180, 180], [-90, 150], [-180, 75], [-400, 400], [-125, 125], [-400, 400]]
links:
  - {{mass_kg: 1, com: [0, 0, 0]}}
  - {{mass_kg: 1, com: [0, 0, 0]}}
  - {{mass_kg: 1, com: [0, 0, 0]}}
  - {{mass_kg: 1, com: [0, 0, 0]}}
  - {{mass_kg: 1, com: [0, 0, 0]}}
  - {{mass_kg: 1, com: [0, 0, 0]}}
gravity: [0, 0, -9.81]
"""


def good_text(convention="dh"):
    return GOOD.format(convention=convention)


def write(tmp_path, text, name="arm.yaml"):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def refused(path, *fragments):
    """load_robot must raise ModelError starting with the path and containing every fragment."""
    with pytest.raises(ModelError) as err:
        load_robot(path)
    message = str(err.value)
    assert message.startswith(str(path)), message
    for fragment in fragments:
        assert fragment in message, message
    return message


def test_the_good_file_loads(tmp_path):
    """The base text the bad files are made from is itself valid (so each refusal is due to its edit)."""
    for convention in ("dh", "mdh"):
        model = load_robot(write(tmp_path, good_text(convention)))
        assert model.n_joints == 6 and len(model.links) == 6


def test_unknown_top_level_key(tmp_path):
    path = write(tmp_path, good_text() + "tool_offset: [0, 0, 100]\n")
    refused(path, "tool_offset", "unknown key")


def test_unknown_joint_key(tmp_path):
    path = write(tmp_path, good_text().replace("{a: 1095, alpha: 0,", "{a: 1095, alfa: 0,"))
    refused(path, "joints[1].alfa", "unknown key")


@pytest.mark.parametrize("key", ["name", "convention", "length_unit", "angle_unit", "joints"])
def test_missing_required_top_level_key(tmp_path, key):
    lines = [ln for ln in good_text().splitlines() if not ln.startswith(f"{key}:")]
    if key == "joints":
        lines = [ln for ln in lines if not ln.startswith("  - {a:")]
    path = write(tmp_path, "\n".join(lines) + "\n")
    refused(path, key, "missing")


def test_missing_required_joint_key(tmp_path):
    path = write(tmp_path, good_text().replace("{a: 175,  alpha: -90, d: 0,    theta: 0}",
                                               "{a: 175,  alpha: -90, theta: 0}"))
    refused(path, "joints[2].d", "missing")


def test_bad_length_unit(tmp_path):
    path = write(tmp_path, good_text().replace("length_unit: mm", "length_unit: inch"))
    refused(path, "length_unit", "inch")


def test_bad_angle_unit(tmp_path):
    path = write(tmp_path, good_text().replace("angle_unit: deg", "angle_unit: grad"))
    refused(path, "angle_unit", "grad")


def test_bad_convention(tmp_path):
    path = write(tmp_path, good_text().replace("convention: dh", "convention: DH"))
    refused(path, "convention", "DH")


@pytest.mark.parametrize("value", ["abc", "true", "[1, 2]", ".nan"])
def test_non_number_value(tmp_path, value):
    path = write(tmp_path, good_text().replace("{a: 1095,", f"{{a: {value},"))
    refused(path, "joints[1].a", "number")


def test_non_number_in_joint_limits(tmp_path):
    path = write(tmp_path, good_text().replace("[-90, 150]", "[-90, high]"))
    refused(path, "joint_limits[1]", "number")


def test_joint_limits_count_mismatch(tmp_path):
    path = write(tmp_path, good_text().replace("[[-180, 180], [-90, 150], ", "[[-90, 150], "))
    refused(path, "joint_limits", "expected 6", "got 5")


@pytest.mark.parametrize("pair", ["[150, -90]", "[150, 150]"])
def test_joint_limit_low_not_below_high(tmp_path, pair):
    path = write(tmp_path, good_text().replace("[-90, 150]", pair))
    refused(path, "joint_limits[1]", "low")


def test_beta_with_convention_dh(tmp_path):
    path = write(tmp_path, good_text("dh").replace("d: 0,    theta: -90}", "d: 0,    theta: -90, beta: 0}"))
    refused(path, "joints[1].beta", "mdh")


def test_beta_with_convention_mdh_is_accepted(tmp_path):
    path = write(tmp_path, good_text("mdh").replace("d: 0,    theta: -90}", "d: 0,    theta: -90, beta: 0.5}"))
    model = load_robot(path)
    assert model.nominal[model.index("beta2")] == pytest.approx(math.radians(0.5), abs=1e-15)


def test_links_count_mismatch(tmp_path):
    text = good_text()
    i = text.index("  - {mass_kg: 1")
    path = write(tmp_path, text[:i] + text[i + len("  - {mass_kg: 1, com: [0, 0, 0]}\n"):])
    refused(path, "links", "expected 6", "got 5")


def test_unknown_link_key(tmp_path):
    path = write(tmp_path, good_text().replace("{mass_kg: 1, com", "{mass: 1, com", 1))
    refused(path, "links[0].mass", "unknown key")


def test_yaml_syntax_error_names_file_and_line(tmp_path):
    lines = good_text().splitlines()
    lines[5] = "  - {a: 175,  alpha: -90, d: 495,  theta: 0"  # line 6: flow mapping never closed
    path = write(tmp_path, "\n".join(lines) + "\n")
    message = refused(path, "YAML")
    prefix = f"{path}:"
    line = int(message[len(prefix):].split(":", 1)[0])
    assert 6 <= line <= 7, message  # the parser notices at the end of line 6 or start of line 7


def test_yaml_syntax_error_on_a_later_line(tmp_path):
    path = write(tmp_path, good_text() + "gravity: [0, 0, -9.81\nname: x\n")
    message = refused(path, "YAML")
    line = int(message[len(f"{path}:"):].split(":", 1)[0])
    n_good = len(good_text().splitlines())
    assert n_good + 1 <= line <= n_good + 3, message


def test_empty_file(tmp_path):
    refused(write(tmp_path, ""), "mapping")


def test_file_not_found(tmp_path):
    path = tmp_path / "nowhere" / "arm.yaml"
    refused(path, "no such file")


def test_unknown_robot_name_lists_the_shipped_ones():
    with pytest.raises(ModelError) as err:
        load_robot("ur99")
    message = str(err.value)
    assert message.startswith("ur99:"), message
    assert "not a shipped robot" in message and "ur5e" in message, message


def test_scientific_notation_is_a_number(tmp_path):
    text = good_text().replace("a: 175,", "a: 1.75e2,", 1)
    assert "1.75e2" in text
    model = load_robot(write(tmp_path, text))
    assert model.nominal[model.index("a1")] == pytest.approx(175.0)


def test_a_key_given_twice_is_refused_naming_the_line(tmp_path):
    text = good_text().replace("theta: 0}", "theta: 0, d: 400}", 1)
    path = write(tmp_path, text)
    line = next(i for i, row in enumerate(text.splitlines(), 1) if "d: 400" in row)
    refused(path, f":{line}:", "d", "twice")
