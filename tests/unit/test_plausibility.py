"""Typical sizes per cause and robot class: the table, its page, the robot's class, and the naming that uses it."""
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from cellcal.cli.main import main
from cellcal.config.robot_files import load_robot
from cellcal.measurements.writer import write_measurements
from cellcal.sims.physics.physical_arm import HiddenEffect
from cellcal.sims.physics.workspace import full_workspace
from cellcal.solvers.analysis import plausibility
from cellcal.solvers.analysis.naming import GROUNDS, name_cause
from cellcal.solvers.analysis.effects import CAUSES

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from support.hidden_cases import _arm  # noqa: E402  (tests/support/hidden_cases.py: a fixture)
from support.naming_stubs import BASELINE, StubScorer, scored  # noqa: E402
from test_docs import table_under  # noqa: E402

DOCS = Path(__file__).resolve().parents[2] / "docs"


def test_the_table_covers_every_cause_and_every_class():
    assert set(plausibility.TYPICAL_MAX) == set(CAUSES) == set(plausibility.QUANTITY)
    for cause, by_class in plausibility.TYPICAL_MAX.items():
        assert set(by_class) == set(plausibility.CLASSES), cause
        assert all(v > 0 for v in by_class.values()), cause
    assert plausibility.DEFAULT_CLASS in plausibility.CLASSES


def test_the_page_carries_the_same_table():
    rows = table_under((DOCS / "causes.md").read_text(encoding="utf-8"),
                       "### Physical plausibility: typical sizes by robot class")
    page = {r["cause"].strip("`"): {k: float(r[k]) for k in plausibility.CLASSES} for r in rows}
    assert page == plausibility.TYPICAL_MAX
    for r in rows:
        assert r["unit"] == plausibility.QUANTITY[r["cause"].strip("`")].unit
    text = (DOCS / "causes.md").read_text(encoding="utf-8")
    assert all(f"`{word}`" in text for word in GROUNDS)


@pytest.mark.parametrize("robot,klass", [("ur10e", "collaborative"), ("ur5e", "collaborative"),
                                         ("elite-ec66", "collaborative"), ("abb-irb4600", "medium")])
def test_the_robot_class_comes_from_the_file(robot, klass):
    got = plausibility.robot_class(load_robot(robot))
    assert got.name == klass, got.reason
    assert got.reason.startswith("link masses sum") == robot.startswith("ur")  # UR files give every mass


def test_heavy_link_masses_make_a_heavy_arm():
    model = load_robot("ur10e")
    heavy = dataclasses.replace(model, links=tuple(dataclasses.replace(l, mass_kg=200.0) for l in model.links))
    assert plausibility.robot_class(heavy).name == "heavy"


def _judged(s, value, klass="collaborative"):
    key = {"joint_compliance": "deflection_rms_deg", "cyclic_joint_error": "amplitude_deg"}[s.cause]
    return dataclasses.replace(s, judged=plausibility.judge(s.cause, {key: value}, klass))


def test_an_implausible_lead_names_nothing_and_the_next_plausible_contender_competes():
    limit = plausibility.TYPICAL_MAX["joint_compliance"]["collaborative"]
    lead = _judged(scored("joint_compliance", 0.50), 3.0 * limit)
    other = _judged(scored("cyclic_joint_error", 0.52), 0.02)  # within the 8% margin: the data do not prefer the lead
    naming = name_cause([lead, other], BASELINE, StubScorer())
    assert naming.named is other and naming.candidates[0] is lead  # the list stays best first
    assert naming.set_aside == (lead,) and "set aside" in naming.plausibility
    assert f"beyond the {limit:g} deg" in naming.plausibility

def test_an_implausible_lead_that_nothing_plausible_replaces_competes_with_its_size_said():
    limit = plausibility.TYPICAL_MAX["joint_compliance"]["collaborative"]
    lead = _judged(scored("joint_compliance", 0.50), 3.0 * limit)
    weak = _judged(scored("cyclic_joint_error", 0.70), 0.02)  # plausible, but 40% behind the lead
    naming = name_cause([lead, weak], BASELINE, StubScorer())
    assert naming.named is lead and naming.set_aside == ()
    assert "no explanation of a plausible size comes within 8% of it" in naming.plausibility
    strict = name_cause([lead, weak], BASELINE, StubScorer(), strict_sizes=True)  # the strict reading: nothing
    assert strict.named is None and strict.set_aside == (lead,) and "set aside" in strict.plausibility


def test_a_plausible_lead_is_named_as_before():
    lead = _judged(scored("joint_compliance", 0.50), 0.05)
    naming = name_cause([lead, _judged(scored("cyclic_joint_error", 0.70), 0.02)], BASELINE, StubScorer())
    assert naming.named is lead and naming.set_aside == () and naming.plausibility == ""


@pytest.mark.parametrize("rms_mm,plausible,strict", [(1.0, True, False), (20.0, False, False), (20.0, False, True)])
def test_compliance_on_a_collaborative_arm_is_judged_by_its_size(rms_mm, plausible, strict, tmp_path, capsys):
    """UR10e, 60 random poses, compliance of joint 2 moving the tool by rms_mm: 1 mm is a deflection of
    about 0.05 deg, 20 mm about 1 deg, twice what collaborative arms show (and nothing else explains it).
    Through the command, `--strict-sizes` for the strict reading."""
    model = load_robot("ur10e")
    arm = _arm(model, 0, (HiddenEffect("joint_compliance", 1, rms_mm=rms_mm),), 1.0)
    run = arm.campaign(full_workspace(model, 60, np.random.default_rng(3)))
    data = tmp_path / "data.csv"
    write_measurements(data, q_rad=run.obs.q, xyz_mm=run.obs.xyz_mm)
    assert main(["analyze", "--robot", "ur10e", "--data", str(data), "--json",
                 *(["--strict-sizes"] if strict else [])]) == 0
    doc = json.loads(capsys.readouterr().out)
    top = doc["candidates"][0]
    assert top["cause"] == "joint_compliance" and top["where"] == {"joint": 2}
    assert doc["robot_class"]["name"] == "collaborative"
    # the linearised size is the hidden one: deflection of joint 2 (rms over the poses) within 20%, the
    # rest being what the geometry absorbs of it and noise (0.02 mm against 1-20 mm of effect)
    true_deg = np.rad2deg(np.sqrt(np.mean(run.true_joint_delta[:, 1] ** 2)))
    assert top["plausibility"]["value"] == pytest.approx(true_deg, rel=0.2)
    assert top["plausibility"]["plausible"] == plausible and ("against" in top) != plausible
    if plausible:
        assert doc["cause"] == "joint_compliance" and "plausibility" not in doc["decided_by"]
        assert "margin" in doc["decided_by"]
        return
    assert "beyond the 0.5 deg" in top["against"] and "plausibility" in doc["decided_by"]
    if strict:  # the lead names nothing: an effect of undecided cause, the grounds say why
        assert doc["cause"] == "none" and doc["undecided"] is not None and "set aside" in doc["grounds"]
    else:  # nothing of plausible size explains the data: named, its size said in the grounds
        assert doc["cause"] == "joint_compliance" and "competes all the same" in doc["grounds"]
