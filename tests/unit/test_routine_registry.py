"""The routine table is the one place that lists a routine: its name, its module, its panel
selector number and its cell file section; its class declares the same, or is refused. The
panel's selector map, the cell file's routine sections and ``cellcal run``'s list all come
from the registry that reads it."""
from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import typing
from types import SimpleNamespace

import pytest

from support.cell_edits import edited_cell
from cellcal.config.cells import CellFileError
from cellcal.daemon.cells import CellDrivers, load_cell
from cellcal.daemon.service import Service, panel_routines
from cellcal.drivers.interfaces import RobotState
from cellcal.routines.framework import registry, table
from cellcal.routines.framework.base import PlanPromise, Routine, RoutineError
from cellcal.routines.framework.registry import RoutineDeclarationError

# the operator panel's routine selector (docs/panel.md), as it has always been
PANEL = {1: "tcp-laser", 2: "tcp-stylus", 3: "tcp-npoint", 4: "handshake", 5: "tracker", 6: "tcf",
         7: "tcp-check", 8: "kinematic-fixture"}


class ProbeRoutine(Routine):
    """A routine declared only here, in a test module."""

    name = "test-probe"
    section = "test_probe"
    selector = 90

    @classmethod
    def read_options(cls, section, cell):
        depth = section.number("depth_mm", 1.0, above=0.0, high=10.0)
        section.done()
        return depth

    def plan(self):
        return []

    def measure(self, devices, robot, plan, progress):
        raise RoutineError("a test routine measures nothing")

    @classmethod
    def solve(cls, dataset, cell, options):
        raise RoutineError("a test routine solves nothing")


@pytest.fixture
def probe():
    registry.register(ProbeRoutine)
    yield ProbeRoutine
    registry.unregister(ProbeRoutine.name)


@pytest.fixture
def probe_cell_file(tmp_path):
    return edited_cell(tmp_path, "sim", {"test_probe": {"depth_mm": 3}}, name="probe.yaml")


def _selected_by_panel(cell, selector: int) -> list[str]:
    """What the service starts when the panel's start is pressed with `selector` set."""
    panel = SimpleNamespace(start_requested=lambda: True, abort_requested=lambda: False, tool_selector=lambda: 0,
                            routine_selector=lambda: selector, set_lamps=lambda **kw: None,
                            confirm_requested=lambda: False)
    robot = SimpleNamespace(state=lambda: RobotState.READY)
    service = Service(cell, CellDrivers(panel=panel, robot=robot), store=None, out_dir="unused")
    started = []
    service.start = lambda routine, tool=0: started.append(routine)
    service.poll_panel()
    return started


def test_the_panel_selector_numbers_are_those_the_panel_has_always_sent():
    assert registry.panel_selectors() == PANEL
    assert panel_routines() == PANEL
    # kinematic-fixture has no selector (registry: None where the panel cannot select a routine)
    assert {registry.routine_class(name).selector: name for name in registry.available()
            if registry.routine_class(name).selector is not None} == PANEL
    assert Service(load_cell("sim"), CellDrivers(), None, out_dir="unused").routines == PANEL


def test_a_routine_declared_once_is_seen_by_the_registry_the_panel_the_cell_file_and_run(probe, probe_cell_file):
    assert "test-probe" in registry.available()
    assert registry.routine_class("test-probe") is ProbeRoutine
    assert "test_probe" in registry.sections()
    # the panel: the service's selector map and a press with the selector at 90
    assert registry.panel_selectors()[90] == "test-probe"
    assert panel_routines()[90] == "test-probe"
    cell = load_cell(probe_cell_file)
    assert _selected_by_panel(cell, 90) == ["test-probe"]
    # the cell file: the section is the routine's, read (and bounded) by it at load
    assert cell.routines["test_probe"] == {"depth_mm": 3}
    assert registry.read_options("test-probe", cell) == 3.0
    bad = edited_cell(probe_cell_file.parent, probe_cell_file, {"test_probe": {"depth_mm": 30}}, name="bad.yaml")
    with pytest.raises(CellFileError) as refused:
        load_cell(bad)
    assert (refused.value.section, refused.value.key) == ("test_probe", "depth_mm"), refused.value
    # cellcal run's list
    from cellcal.cli import run as run_cmd
    sub = argparse.ArgumentParser().add_subparsers()
    run_cmd.add_parser(sub)
    (routine_arg,) = [a for a in sub.choices["run"]._actions if a.dest == "routine"]
    assert "test-probe" in routine_arg.help


def test_without_the_declaration_its_section_and_selector_are_unknown(probe_cell_file):
    assert "test-probe" not in registry.available()
    assert 90 not in registry.panel_selectors()
    with pytest.raises(CellFileError, match="unknown section") as refused:
        load_cell(probe_cell_file)
    assert (refused.value.section, refused.value.key) == (None, "test_probe"), refused.value
    cell = load_cell("sim")
    assert _selected_by_panel(cell, 90) == ["selector 90"]  # refused by run() as no such routine


def _routine(**declared) -> type[Routine]:
    return type("Clash", (ProbeRoutine,), {"__module__": __name__, **declared})


@pytest.mark.parametrize("declared, needles", [
    ({"name": "clash", "section": "clash", "selector": 1},
     ["'clash'", "panel selector 1", "routine 'tcp-laser'", "cellcal.routines.tcp_laser.TcpLaser"]),
    ({"name": "clash", "section": "clash", "selector": 6}, ["panel selector 6", "routine 'tcf'"]),
    ({"name": "tcf", "section": "clash", "selector": None}, ["name 'tcf'", "routine 'tcf'"]),
    ({"name": "clash", "section": "tcp_laser", "selector": None}, ["section 'tcp_laser'", "routine 'tcp-laser'"]),
])
def test_a_second_routine_claiming_a_selector_name_or_section_is_refused(declared, needles):
    before = registry.panel_selectors()
    with pytest.raises(RoutineDeclarationError) as err:
        registry.register(_routine(**declared))
    for needle in needles:
        assert needle in str(err.value), str(err.value)
    assert registry.panel_selectors() == before and "clash" not in registry.available()


def test_two_test_routines_on_one_selector_are_refused(probe):
    with pytest.raises(RoutineDeclarationError, match="'other' .* claims panel selector 90, which routine "
                                                      "'test-probe'"):
        registry.register(_routine(name="other", section="other", selector=90))


@pytest.mark.parametrize("declared, needle", [
    ({"name": "", "section": "clash"}, "declares no name"),
    ({"name": "clash", "section": ""}, "declares no cell file section"),
    ({"name": "clash", "section": "tool"}, "one of the cell file's own"),
    ({"name": "clash", "section": "clash", "selector": 0}, "panel selector 0"),
    ({"name": "clash", "section": "clash", "selector": True}, "panel selector True"),
    ({"name": "clash", "section": "clash", "selector": 70000}, "panel selector 70000"),
])
def test_an_incomplete_or_impossible_declaration_is_refused(declared, needle):
    with pytest.raises(RoutineDeclarationError, match=needle):
        registry.register(_routine(**declared))


def test_the_registry_imports_no_routine_until_it_is_asked():
    code = ("import sys, json\nfrom cellcal.routines.framework import registry\n"
            "before = set(sys.modules)\n"
            "names = registry.available()\n"
            "homes = sorted({registry.routine_class(n).__module__ for n in names})\n"
            "print(json.dumps([sorted(before & set(homes)), homes, names]))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    loaded_before, homes, names = json.loads(proc.stdout)
    assert loaded_before == []
    assert len(homes) == 8 and set(names) >= {"tcp-laser", "tcp-stylus", "tcp-npoint", "tcf", "tracker", "handshake",
                                              "tcp-check", "kinematic-fixture"}


def test_listing_the_routines_and_the_panel_selectors_imports_no_routine():
    code = ("import sys, json\nfrom cellcal.routines.framework import registry, table\n"
            "lists = [registry.available(), registry.panel_selectors(), registry.sections()]\n"
            "print(json.dumps(sorted(set(sys.modules) & {row.module for row in table.ROUTINES.values()})))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert json.loads(proc.stdout) == []


def test_a_class_that_differs_from_its_row_of_the_routine_table_is_refused(monkeypatch):
    monkeypatch.setitem(table.ROUTINES, "tcf", dataclasses.replace(table.ROUTINES["tcf"], selector=9))
    monkeypatch.setattr(registry, "_listed", None)
    monkeypatch.setattr(registry, "_imported", {})
    assert registry.panel_selectors()[9] == "tcf"  # the table answers without importing
    with pytest.raises(RoutineDeclarationError, match=r"cellcal\.routines\.tcf\.Tcf declares panel selector 6; "
                                                      r"the routine table .* lists 9 for 'tcf'"):
        registry.routine_class("tcf")


def _camel(name: str) -> str:
    return "".join(part.capitalize() for part in name.split("-"))


@pytest.mark.parametrize("name", list(PANEL.values()))
def test_every_routine_names_its_options_and_gives_one_kind_of_design(name):
    cls = registry.routine_class(name)
    assert typing.get_type_hints(cls.read_options)["return"].__name__ == f"{_camel(name)}Options"
    assert typing.get_type_hints(cls.design)["return"] in (PlanPromise, PlanPromise | None)


@pytest.mark.parametrize("name, cell_name, unit", [("tcp-npoint", "sim", "mm"), ("tcf", "sim", "deg"),
                                                   ("handshake", "sim-dual", "mm")])
def test_a_design_judged_before_moving_has_the_same_shape_in_every_routine(name, cell_name, unit):
    cell = load_cell(cell_name)
    routine = registry.routine_class(name)(cell, registry.read_options(name, cell))
    design = routine.check_design()
    assert isinstance(design, PlanPromise) and design.unit == unit
    assert 0 < design.expected_error and 1 <= design.condition < 1e3
