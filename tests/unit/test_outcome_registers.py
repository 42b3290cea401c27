"""The outcome registers' encoding (daemon/outcome.py, docs/panel.md "Outcome registers")."""
from __future__ import annotations

import numpy as np
import pytest

from cellcal.daemon import outcome
from cellcal.drivers.modbus.panel import ModbusPanel, PanelMap
from cellcal.drivers.registry import DriverConfigError
from cellcal.routines.framework import tool_frame


def test_a_change_round_trips_in_thousandths_signed_and_saturated():
    change = {"x_mm": -0.123, "y_mm": 0.0004, "z_mm": 40.0, "tilt_x_deg": -50.0, "tilt_y_deg": None}
    raw = outcome.registers("corrected", 1, change)
    assert all(0 <= v <= 0xFFFF for v in raw.values())
    assert raw["change_x"] == 0x10000 - 123  # two's complement of -123 thousandths
    back = outcome.decoded(raw)
    assert back["verdict"] == "corrected" and back["tool_id"] == 1
    # a thousandth is the register's resolution: what comes back is within half of one
    assert back["x_mm"] == pytest.approx(-0.123, abs=5e-4) and back["y_mm"] == 0.0
    assert back["z_mm"] == 32.767 and back["tilt_x_deg"] == -32.767  # saturated, never wrapped
    assert back["tilt_y_deg"] is None  # not determined reads 0x8000
    assert raw["tilt_y"] == 0x8000


def test_no_result_reads_not_determined_and_verdict_zero():
    raw = outcome.registers(None, 0, None)
    assert raw["verdict"] == 0 and raw["tool_id"] == 0
    assert {raw[k] for k in outcome.CHANGE_KEYS} == {0x8000}


def test_the_change_of_a_tip_only_result_leaves_the_tilt_undetermined():
    old = np.array([0.001, 0.0, 0.15, 0.0, 0.0, 0.0])
    new = np.array([0.0012, -0.0003, 0.1499, 0.0, np.radians(0.5), 0.0])
    both = tool_frame.change(new, old)
    assert both["x_mm"] == pytest.approx(0.2) and both["y_mm"] == pytest.approx(-0.3)
    assert both["z_mm"] == pytest.approx(-0.1)
    assert both["tilt_x_deg"] == pytest.approx(0.5) and both["tilt_y_deg"] == pytest.approx(0.0, abs=1e-12)
    tip = tool_frame.change(new, old, tool_frame.TIP_ONLY)
    assert tip["tilt_x_deg"] is None and tip["tilt_y_deg"] is None and tip["x_mm"] == both["x_mm"]


def test_outcome_registers_are_addresses_of_their_own():
    # selector, result code, run counter, the 7 outcome registers, tool selector, mounted tool and placement
    assert len(set(PanelMap().holding_registers())) == len(PanelMap().holding_registers()) == 13
    with pytest.raises(DriverConfigError, match="share an address"):
        ModbusPanel.check_options(port=502, unit_id=1, timeout_s=1.0,
                                  **{**PanelMap().__dict__, "tilt_y_register": 1})
