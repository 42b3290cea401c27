"""A check's verdict as a pure function of the measured change, its uncertainty and the bands
(solvers/tool_frames/verdict.py), at the edges of each band.

Tolerances: the bands and the uncertainties here are dyadic (0.375, 0.125, 1.5 ...), so a
change exactly at an edge, and K_SIGMA times an uncertainty, are exact in floating point and
the edge itself is tested, not a rounding of it. HAIR, the step either side of an edge, is
1e-9 (mm or deg): a million times finer than the finest change a check resolves (its 1-sigma
uncertainty is some 0.005 mm at best; the panel carries 0.001), and ten million times coarser
than the rounding of numbers of this size (1e-16): a change a hair beyond a band is beyond it.
"""
from __future__ import annotations

import json

import pytest

from cellcal.config.cells import Bands
from cellcal.daemon import outcome
from cellcal.solvers.tool_frames.verdict import (K_SIGMA, Measured, Verdict, check_verdict, drift_verdict,
                                                  judge_part)

HAIR = 1e-9  # see the module's doc
BANDS = Bands(inner_mm=0.375, outer_mm=1.5, inner_deg=0.1875, outer_deg=0.75, drift_mm=0.5, drift_deg=0.25)
SURE = {"tip": 0.03125, "axis": 0.015625}  # 1 sigma well inside a third of each inner band: determined
INNER = {"tip": BANDS.inner_mm, "axis": BANDS.inner_deg}
OUTER = {"tip": BANDS.outer_mm, "axis": BANDS.outer_deg}


def verdict_of(part: str, size: float, std: float | None = None, gates_passed: bool = True):
    """The check's verdict with `part` changed by `size` (known to `std`), the other part
    determined and unchanged."""
    changed = Measured(size, SURE[part] if std is None else std)
    still = {"tip": Measured(0.0, SURE["tip"]), "axis": Measured(0.0, SURE["axis"])}
    still[part] = changed
    return check_verdict(still["tip"], still["axis"], BANDS, gates_passed)


@pytest.mark.parametrize("part", ["tip", "axis"])
def test_a_change_at_the_inner_band_is_ok_and_a_hair_beyond_it_corrected(part):
    assert verdict_of(part, INNER[part] - HAIR).verdict is Verdict.OK
    assert verdict_of(part, INNER[part]).verdict is Verdict.OK  # within means up to and including the band
    beyond = verdict_of(part, INNER[part] + HAIR)
    assert beyond.verdict is Verdict.CORRECTED and getattr(beyond, part).beyond_inner
    assert not getattr(beyond, "axis" if part == "tip" else "tip").beyond_inner


@pytest.mark.parametrize("part", ["tip", "axis"])
def test_a_change_at_the_outer_band_is_corrected_and_a_hair_beyond_it_an_alarm(part):
    assert verdict_of(part, OUTER[part]).verdict is Verdict.CORRECTED
    beyond = verdict_of(part, OUTER[part] + HAIR)
    assert beyond.verdict is Verdict.ALARM and getattr(beyond, part).beyond_outer


@pytest.mark.parametrize("part", ["tip", "axis"])
def test_a_part_is_determined_while_k_sigma_fits_in_its_inner_band(part):
    edge = INNER[part] / K_SIGMA  # exact: 0.125 mm, 0.0625 deg
    assert edge * K_SIGMA == INNER[part]
    assert judge_part(Measured(0.0, edge), INNER[part], OUTER[part]).determined
    assert not judge_part(Measured(0.0, edge + HAIR), INNER[part], OUTER[part]).determined
    assert not judge_part(None, INNER[part], OUTER[part]).measured


def test_nothing_determined_is_an_alarm_whatever_the_change():
    loose = INNER["tip"] / K_SIGMA + HAIR
    assert check_verdict(Measured(0.0, loose), None, BANDS, True).verdict is Verdict.ALARM
    assert check_verdict(Measured(0.0, INNER["tip"] / K_SIGMA), None, BANDS, True).verdict is Verdict.OK


@pytest.mark.parametrize("part", ["tip", "axis"])
def test_a_part_not_determined_meets_no_inner_band_and_the_outer_only_by_its_k_sigma_lower_bound(part):
    """Known to 2 thirds of its inner band (not determined): a change far beyond the inner band
    is no correction, and it is an alarm only once even size - K_SIGMA std is beyond the outer."""
    std = 2 * INNER[part] / K_SIGMA  # 0.25 mm, 0.125 deg: exact
    assert verdict_of(part, 4 * INNER[part], std).verdict is Verdict.OK
    edge = OUTER[part] + K_SIGMA * std  # its lower bound exactly at the outer band
    at = verdict_of(part, edge, std)
    assert at.verdict is Verdict.OK and not getattr(at, part).determined and not getattr(at, part).beyond_outer
    beyond = verdict_of(part, edge + HAIR, std)
    assert beyond.verdict is Verdict.ALARM and getattr(beyond, part).beyond_outer


def test_a_failed_gate_is_an_alarm_before_ok_or_corrected():
    assert verdict_of("tip", 0.0, gates_passed=False).verdict is Verdict.ALARM
    assert verdict_of("tip", INNER["tip"] + HAIR, gates_passed=False).verdict is Verdict.ALARM


def test_a_check_of_one_height_is_judged_by_its_tip_alone():
    judged = check_verdict(Measured(INNER["tip"] + HAIR, SURE["tip"]), None, BANDS, True)
    assert judged.verdict is Verdict.CORRECTED and not judged.axis.measured and not judged.axis.determined


@pytest.mark.parametrize("verdict", [Verdict.OK, Verdict.CORRECTED])
def test_an_ok_or_corrected_check_drifts_a_hair_beyond_the_drift_alarm(verdict):
    assert drift_verdict(verdict, BANDS.drift_mm, None, BANDS) is verdict
    assert drift_verdict(verdict, BANDS.drift_mm + HAIR, None, BANDS) is Verdict.DRIFT
    assert drift_verdict(verdict, None, BANDS.drift_deg, BANDS) is verdict
    assert drift_verdict(verdict, None, BANDS.drift_deg + HAIR, BANDS) is Verdict.DRIFT
    assert drift_verdict(verdict, 1e3, 1e3, Bands()) is verdict  # the drift alarm is off unless set


def test_an_alarm_stays_an_alarm_and_a_calibration_has_no_verdict():
    assert drift_verdict(Verdict.ALARM, 1e3, 1e3, BANDS) is Verdict.ALARM
    assert drift_verdict(None, 1e3, 1e3, BANDS) is None


def test_the_verdict_is_a_pure_function_of_its_arguments():
    tip, axis = Measured(INNER["tip"] + HAIR, SURE["tip"]), Measured(0.0, SURE["axis"])
    first = check_verdict(tip, axis, BANDS, True)
    assert check_verdict(tip, axis, BANDS, True) == first
    assert (tip, axis) == (Measured(INNER["tip"] + HAIR, SURE["tip"]), Measured(0.0, SURE["axis"]))


def test_a_verdict_reads_as_its_word_in_json_and_as_its_number_in_the_registers():
    assert [v.value for v in Verdict] == ["ok", "corrected", "alarm", "drift"]
    assert json.dumps({"verdict": Verdict.DRIFT}) == '{"verdict": "drift"}' and Verdict("alarm") is Verdict.ALARM
    assert [outcome.registers(v, 1, None)["verdict"] for v in (None, *Verdict)] == [0, 1, 2, 3, 4]
    assert [outcome.registers(v.value, 1, None)["verdict"] for v in Verdict] == [1, 2, 3, 4]
