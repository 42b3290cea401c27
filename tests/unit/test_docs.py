"""The README and the pages in docs/ say what the code does: the panel's register map, the
exit-status table of the command line, the cause ids, the sub-commands, the README's routine
table, the ``--help`` blocks the pages show; the README stays short, its two commands are the
Makefile's, every page is in the index and every link between them resolves; and nothing in
the project points at the specification files it no longer needs (``spec/...``).

Each check compares two independent sources, a table parsed out of a page and the
constants or behaviour of the code, and returns the differences it finds; the tests
that tamper with a copy of a page show that every check can fail.
"""
from __future__ import annotations

import dataclasses
import importlib
import inspect
import json
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
PACKAGE_ROOMS = ("cli", "config", "daemon", "drivers", "measurements", "programs", "reports", "routines", "sims", "solvers")


# -- reading markdown tables ------------------------------------------------------------------------------


def _cells(line: str) -> list[str]:
    inner = line.strip()
    inner = inner[1:] if inner.startswith("|") else inner
    inner = inner[:-1] if inner.endswith("|") and not inner.endswith("\\|") else inner
    return [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", inner)]


def table_under(text: str, heading: str) -> list[dict[str, str]]:
    """The rows of the first table after the line `heading` (and before the next heading),
    as dicts keyed by the table's header cells."""
    lines = text.splitlines()
    try:
        i = next(k for k, line in enumerate(lines) if line.strip() == heading) + 1
    except StopIteration:
        raise LookupError(f"no heading {heading!r}") from None
    while i < len(lines) and not lines[i].lstrip().startswith("|"):
        if lines[i].startswith("#"):
            raise LookupError(f"no table under {heading!r}")
        i += 1
    block = []
    while i < len(lines) and lines[i].lstrip().startswith("|"):
        block.append(lines[i])
        i += 1
    if len(block) < 3 or not set(block[1].replace("|", "").strip()) <= set("-: "):
        raise LookupError(f"the table under {heading!r} has no header and separator line")
    header = _cells(block[0])
    return [dict(zip(header, _cells(line))) for line in block[2:]]


def _code(text: str) -> str:
    return text.strip().strip("`").strip()


def _words(text: str) -> str:
    return " ".join(text.split())


def _backticked(text: str) -> list[str]:
    return re.findall(r"`([^`]+)`", text)


# -- the panel: docs/panel.md against drivers.modbus.panel, daemon.panel and daemon.result_codes --------------


def _selector_map() -> dict[int, str]:
    """The routine selector values as the daemon uses them."""
    panel = importlib.import_module("cellcal.daemon.panel")
    return {int(k): v for k, v in panel.panel_routines().items()}


def panel_mismatches(text: str) -> list[str]:
    """Every difference between the tables of a panel page and the code's constants."""
    from cellcal.daemon.result_codes import RESULT_MEANINGS, ResultCode
    from cellcal.drivers.modbus.panel import ModbusPanel, PanelMap

    out = []
    defaults = PanelMap()
    ctor = {name: p.default for name, p in inspect.signature(ModbusPanel.__init__).parameters.items()}
    map_fields = [f.name for f in dataclasses.fields(PanelMap)]

    for heading, suffix in (("## Coils", "_coil"), ("## Holding registers", "_register")):
        try:
            rows = table_under(text, heading)
        except LookupError as exc:
            return [str(exc)]
        documented = {}
        for row in rows:
            option = _code(row.get("option", ""))
            try:
                documented[option] = int(row.get("address", ""))
            except ValueError:
                out.append(f"{heading}: address {row.get('address')!r} of {option} is not a number")
        expected = {f: getattr(defaults, f) for f in map_fields if f.endswith(suffix)}
        for option in sorted(set(expected) | set(documented)):
            if option not in documented:
                out.append(f"{heading}: {option} (address {expected[option]}) is missing")
            elif option not in expected:
                out.append(f"{heading}: {option} is not an address of PanelMap")
            elif documented[option] != expected[option]:
                out.append(f"{heading}: {option} is {documented[option]} in the page, {expected[option]} in PanelMap")
            elif ctor.get(option) != documented[option]:
                out.append(f"{heading}: {option} is {documented[option]} in the page, {ctor.get(option)} as "
                           "ModbusPanel's default")

    try:
        connection = table_under(text, "## Connecting a panel")
    except LookupError as exc:
        return out + [str(exc)]
    for row in connection:
        option, value = _code(row["option"]), row["default"].strip()
        if option not in ctor:
            out.append(f"connection: {option} is not an option of ModbusPanel")
        elif str(ctor[option]) != value:
            out.append(f"connection: {option} defaults to {value} in the page, {ctor[option]!r} in ModbusPanel")

    try:
        documented_selector = {int(r["value"]): _code(r["routine"]) for r in table_under(text, "## Routine selector")}
    except (LookupError, ValueError, KeyError) as exc:
        return out + [f"routine selector table: {exc}"]
    actual = _selector_map()
    for value in sorted(set(actual) | set(documented_selector)):
        if documented_selector.get(value) != actual.get(value):
            out.append(f"routine selector {value}: {documented_selector.get(value)!r} in the page, "
                       f"{actual.get(value)!r} in the daemon")

    try:
        documented_codes = {int(r["code"]): (_code(r["name"]), _words(r["meaning"]))
                            for r in table_under(text, "## Result codes")}
    except (LookupError, ValueError, KeyError) as exc:
        return out + [f"result code table: {exc}"]
    actual_codes = {int(c): (c.name, _words(RESULT_MEANINGS[c])) for c in ResultCode}
    for code in sorted(set(actual_codes) | set(documented_codes)):
        if documented_codes.get(code) != actual_codes.get(code):
            out.append(f"result code {code}: {documented_codes.get(code)} in the page, {actual_codes.get(code)} "
                       "in the daemon")
    return out


def test_panel_page_matches_the_register_map_selector_and_result_codes():
    assert panel_mismatches((DOCS / "panel.md").read_text(encoding="utf-8")) == []


@pytest.mark.parametrize("old,new", [
    ("| 8 | busy lamp |", "| 7 | busy lamp |"),                      # a coil address
    ("| 2 | run counter |", "| 3 | run counter |"),                  # a holding register address
    ("| `port` | 502 |", "| `port` | 503 |"),                        # a connection default
    ("| 6 | `tcf` |", "| 7 | `tcf` |"),                              # a selector number
    ("| 1 | `tcp-laser` |", "| 1 | `tcp-stylus` |"),                # a selector's routine
    ("| 31 | `GATE_FAILED` |", "| 33 | `GATE_FAILED` |"),            # a result code
    ("| 40 | `ABORTED` | aborted by the operator", "| 40 | `ABORTED` | aborted by the user"),  # a meaning
])
def test_panel_check_catches_a_changed_number_or_meaning(tmp_path, old, new):
    text = (DOCS / "panel.md").read_text(encoding="utf-8")
    assert text.count(old) == 1, f"the page no longer has {old!r}; update this test"
    tampered = tmp_path / "panel.md"
    tampered.write_text(text.replace(old, new), encoding="utf-8")
    assert panel_mismatches(tampered.read_text(encoding="utf-8"))


def test_panel_check_catches_a_dropped_row(tmp_path):
    text = (DOCS / "panel.md").read_text(encoding="utf-8")
    row = next(line for line in text.splitlines() if line.startswith("| 41 |"))
    assert panel_mismatches(text.replace(row + "\n", ""))


# -- the command line: docs/cli.md against cellcal.cli.main -----------------------------------------------


def _exception_factories() -> dict:
    """Every kind of error the exit-status table names, built as the code raises it."""
    from cellcal.cli.common import ReportError, UsageError
    from cellcal.config.cells import CellFileError
    from cellcal.config.reader import ConfigError
    from cellcal.config.robot_files import ModelError
    from cellcal.daemon.claims import Holder, InUseError
    from cellcal.drivers.interfaces import DeviceError
    from cellcal.drivers.registry import DriverConfigError
    from cellcal.measurements.table import DatasetError
    from cellcal.routines.framework.base import RoutineError
    from cellcal.solvers.identification.identify import IdentificationError

    return {
        "DeviceError": lambda: DeviceError("robot", "connection lost"),
        "InUseError": lambda: InUseError("robot 10.0.0.2", Holder(812, "cellcal daemon --cell cell.yaml")),
        "RoutineError": lambda: RoutineError("no edges seen"),
        "ValueError": lambda: ValueError("singular"),
        "IdentificationError": lambda: IdentificationError("degenerate data"),
        "LinAlgError": lambda: np.linalg.LinAlgError("SVD did not converge"),
        "RuntimeError": lambda: RuntimeError("did not start"),
        "MemoryError": lambda: MemoryError("too large"),
        "KeyboardInterrupt": lambda: KeyboardInterrupt(),
        "UsageError": lambda: UsageError("--folds must be at least 2"),
        "ReportError": lambda: ReportError("--report out: cannot write"),
        "DatasetError": lambda: DatasetError("cal.csv:3: bad"),
        "ConfigError": lambda: ConfigError("bad value", source="cell.yaml", key="x"),
        "ModelError": lambda: ModelError("unknown key", source="robot.yaml", key="y"),
        "CellFileError": lambda: CellFileError("unknown key", source="cell.yaml", key="z"),
        "DriverConfigError": lambda: DriverConfigError("unknown option", key="speed"),
        "OSError": lambda: FileNotFoundError(2, "No such file or directory", "cal.csv"),
        "Exception": lambda: KeyError("a defect"),  # any other kind
    }


def exit_table(text: str) -> dict[str, int]:
    """Kind of error (or ``argparse``, or ``success``) -> exit status, from the page's table."""
    out = {}
    for row in table_under(text, "## Exit status"):
        status = int(_code(row["status"]))
        names = _backticked(row["raised as"])
        if not names:
            out["success"] = status
        for name in names:
            if name in out:
                raise ValueError(f"{name} is in two rows (status {out[name]} and {status})")
            out[name] = status
    return out


def _status_of(exc: BaseException, capsys) -> tuple[int, str]:
    from cellcal.cli.main import _run

    def raiser(args):
        raise exc

    status = _run(SimpleNamespace(func=raiser, json=True, command="test"))
    return status, capsys.readouterr().out


def exit_table_mismatches(text: str, capsys) -> list[str]:
    """Differences between the page's exit-status table and what the command line does with
    each kind of error it names."""
    from cellcal.cli.main import main

    out = []
    try:
        table = exit_table(text)
    except (LookupError, ValueError, KeyError) as exc:
        return [f"exit-status table: {exc}"]
    factories = _exception_factories()
    for name in sorted(set(factories) - set(table)):
        out.append(f"{name} is not in the exit-status table")
    if table.get("success") != 0:
        out.append(f"success is status {table.get('success')} in the table, 0 in the code")
    for name, status in sorted(table.items()):
        if name == "success":
            continue
        if name == "argparse":
            with pytest.raises(SystemExit) as exit_:
                main(["identify"])  # the required options missing
            capsys.readouterr()
            if exit_.value.code != status:
                out.append(f"argparse errors: status {status} in the table, {exit_.value.code} from the code")
            continue
        if name not in factories:
            out.append(f"{name}: a kind of error this test does not know (add it to _exception_factories)")
            continue
        got, stdout = _status_of(factories[name](), capsys)
        if got != status:
            out.append(f"{name}: status {status} in the table, {got} from the code")
        elif name == "ReportError":  # the result is on stdout already: no error object after it
            if stdout:
                out.append(f"{name}: --json printed {stdout!r} after the result")
        else:
            obj = json.loads(stdout) if stdout.strip() else None
            if not (isinstance(obj, dict) and set(obj) == {"error"} and obj["error"].get("code") == got
                    and isinstance(obj["error"].get("message"), str)):
                out.append(f"{name}: --json printed {stdout!r}, not one error object with code {got}")
    return out


def test_exit_status_table_matches_what_the_command_line_does(capsys):
    assert exit_table_mismatches((DOCS / "cli.md").read_text(encoding="utf-8"), capsys) == []


@pytest.mark.parametrize("old,new", [
    ("`DeviceError`, `RoutineError`", "`RoutineError`"),  # a kind dropped from the table
    ("| 2 | bad usage or bad input | `argparse`, `UsageError`", "| 1 | bad usage or bad input | `argparse`, `UsageError`"),
    ("`Exception` (any other: a defect) |", "`Exception` (any other: a defect), `DatasetError` |"),
])
def test_exit_status_check_catches_a_wrong_table(tmp_path, capsys, old, new):
    text = (DOCS / "cli.md").read_text(encoding="utf-8")
    assert text.count(old) == 1, f"the page no longer has {old!r}; update this test"
    tampered = tmp_path / "cli.md"
    tampered.write_text(text.replace(old, new), encoding="utf-8")
    assert exit_table_mismatches(tampered.read_text(encoding="utf-8"), capsys)


def test_the_command_line_ends_with_the_documented_status(tmp_path, capsys):
    """Bad usage, bad input, a failed computation and a success, run through cellcal.cli.main.main."""
    from cellcal.cli.main import main
    from cellcal.measurements.writer import write_measurements

    table = exit_table((DOCS / "cli.md").read_text(encoding="utf-8"))

    with pytest.raises(SystemExit) as exit_:
        main(["identify", "--robot", "ur5e", "--json"])  # --data missing
    assert exit_.value.code == table["argparse"] == 2
    capsys.readouterr()

    bad = tmp_path / "bad.csv"
    bad.write_text("q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,x_mm,y_mm,z_mm\n0,0,0,0,0,abc,1,2,3\n")
    status = main(["identify", "--robot", "ur5e", "--data", str(bad), "--json"])
    error = json.loads(capsys.readouterr().out)["error"]
    assert status == error["code"] == table["DatasetError"] == 2
    assert "bad.csv:2" in error["message"]

    degenerate = tmp_path / "degenerate.csv"  # positions without spread: no calibration in them
    q = np.random.default_rng(0).uniform(-1.0, 1.0, (12, 6))
    write_measurements(degenerate, q_rad=q, xyz_mm=np.tile([900.0, 100.0, 400.0], (12, 1)))
    status = main(["identify", "--robot", "ur5e", "--data", str(degenerate), "--json"])
    error = json.loads(capsys.readouterr().out)["error"]
    assert status == error["code"] == table["IdentificationError"] == 1

    status = main(["run", "tcp-laser", "--cell", "sim", "--dry-run", "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert status == table["success"] == 0 and doc["within_limits"] is True


def _subparser(parser, words):
    for word in words:
        action = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
        parser = action.choices[word]
    return parser


def test_cli_page_lists_every_sub_command_and_which_take_json():
    from cellcal.cli.main import COMMANDS, build_parser

    rows = table_under((DOCS / "cli.md").read_text(encoding="utf-8"), "## Sub-commands")
    documented = {tuple(_code(r["command"]).split()[1:]): r["`--json`"].strip() for r in rows}
    assert {words[0] for words in documented} == set(COMMANDS)
    parser = build_parser(every=True)
    for words, json_column in documented.items():
        sub = _subparser(parser, words)
        assert not any(a.__class__.__name__ == "_SubParsersAction" for a in sub._actions), \
            f"cellcal {' '.join(words)} has sub-commands: document each"
        takes_json = "--json" in sub._option_string_actions
        assert json_column == ("yes" if takes_json else "no"), f"cellcal {' '.join(words)}: --json"


# -- the README: short, its two commands, its routine table against the registry ---------------------------


README = ROOT / "README.md"
README_MAX_LINES = 200


def test_the_readme_stays_short():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines; move detail to a page of docs/"


def test_the_readme_shows_the_two_commands_and_the_makefile_has_them():
    text = README.read_text(encoding="utf-8")
    targets = set(re.findall(r"^([a-z][\w-]*):", (ROOT / "Makefile").read_text(encoding="utf-8"), re.M))
    for command in ("make demo", "make test"):
        assert re.search(rf"^{command}\s+#", text, re.M), f"the README no longer shows `{command}`"
        assert command.split()[1] in targets


def routine_table_mismatches(text: str) -> list[str]:
    """Differences between the README's routine table and the routine classes the registry finds:
    every routine in it once, with its panel selector and its cell file section."""
    from cellcal.routines.framework import registry

    try:
        rows = table_under(text, "## Routines")
    except LookupError as exc:
        return [str(exc)]
    out, documented = [], {}
    for row in rows:
        name = _code(row.get("routine", ""))
        if name in documented:
            out.append(f"{name} is in the table twice")
        documented[name] = row
    for name in sorted(set(documented) | set(registry.available())):
        if name not in documented:
            out.append(f"routine {name} is missing from the table")
            continue
        try:
            cls = registry.routine_class(name)
        except KeyError:
            out.append(f"{name} is in the table but is no routine")
            continue
        row = documented[name]
        selector = row.get("panel selector", "").strip()
        expected = "—" if cls.selector is None else str(cls.selector)
        if selector != expected:
            out.append(f"{name}: panel selector {selector!r} in the table, {expected!r} in {cls.__module__}")
        if _code(row.get("cell section", "")) != cls.section:
            out.append(f"{name}: section {row.get('cell section')!r} in the table, {cls.section!r} in {cls.__module__}")
        if not row.get("what it measures", "").strip():
            out.append(f"{name}: says nothing of what it measures")
    return out


def test_the_readme_routine_table_matches_the_registry():
    assert routine_table_mismatches(README.read_text(encoding="utf-8")) == []


@pytest.mark.parametrize("old,new", [
    ("| 7 | `tcp_check` |", "| 6 | `tcp_check` |"),              # a selector number
    ("| 8 | `kinematic_fixture` |", "| 8 | `fixture` |"),           # a section
])
def test_the_routine_table_check_catches_a_wrong_row(old, new):
    text = README.read_text(encoding="utf-8")
    assert text.count(old) == 1, f"the README no longer has {old!r}; update this test"
    assert routine_table_mismatches(text.replace(old, new))


def test_the_routine_table_check_catches_a_dropped_routine():
    text = README.read_text(encoding="utf-8")
    row = next(line for line in text.splitlines() if line.startswith("| `tcp-check` |"))
    assert routine_table_mismatches(text.replace(row + "\n", ""))


# -- the --help blocks a page shows are what the command prints ---------------------------------------------


HELP_BLOCK = re.compile(r"<summary><code>cellcal ([\w-]+) --help</code></summary>\s*```\n(.*?)```", re.S)


def help_blocks() -> list[tuple[str, str, str]]:
    """(page, sub-command, the block's text) of every ``cellcal X --help`` block in docs/."""
    return [(page.name, m.group(1), m.group(2)) for page in sorted(DOCS.glob("*.md"))
            for m in HELP_BLOCK.finditer(page.read_text(encoding="utf-8"))]


def test_the_pages_show_some_help_blocks():
    assert {command for _, command, _ in help_blocks()} >= {"compensate", "iso9283"}


@pytest.mark.parametrize("page,command", [(p, c) for p, c, _ in help_blocks()])
def test_a_help_block_is_what_the_command_prints(page, command, capsys, monkeypatch):
    from cellcal.cli.main import main

    monkeypatch.setenv("COLUMNS", "80")  # argparse wraps at the terminal's width; the pages at 80
    block = next(text for p, c, text in help_blocks() if (p, c) == (page, command))
    with pytest.raises(SystemExit):
        main([command, "--help"])
    assert capsys.readouterr().out == block, f"{page}: the `cellcal {command} --help` block is out of date"


# -- the index lists every page ------------------------------------------------------------------------------


def test_the_docs_index_and_the_readme_list_every_page():
    pages = {p.name for p in DOCS.glob("*.md")} - {"README.md"}
    index = (DOCS / "README.md").read_text(encoding="utf-8")
    readme = README.read_text(encoding="utf-8")
    assert {p for p in pages if f"]({p})" not in index} == set()
    assert {p for p in pages if f"](docs/{p})" not in readme} == set()


# -- causes: docs/causes.md against solvers.analysis.effects ------------------------------------------------------


def test_causes_page_names_exactly_the_cause_ids():
    from cellcal.solvers.analysis.effects import IDS

    rows = table_under((DOCS / "causes.md").read_text(encoding="utf-8"),
                       "# Causes: what `cellcal analyze` may name")
    assert [_code(r["id"]) for r in rows] == list(IDS)


# -- pointers: no specification paths, no reading-list file names, no dead links in docs/ --------------


STALE = (
    (re.compile(r"shared/spec|(?<![\w./-])spec/[\w.-]*"), "a specification path"),
    (re.compile(r"\b\d{3}_[0-9a-f]{16}(\.txt)?\b"), "a reading-list file name"),
    (re.compile(r"shared/seeds|\bseeds/\d{3}\b|\b[Ss]eeds? \d{3}\b"), "a paper cited by its reading-list number"),
)


def stale_references(text: str) -> list[str]:
    """Each line of `text` that points at the specification files or cites a paper by its
    place in the reading list, with what it is."""
    out = []
    for number, line in enumerate(text.splitlines(), start=1):
        for pattern, what in STALE:
            if pattern.search(line):
                out.append(f"{number}: {what}: {line.strip()}")
    return out


def _project_texts() -> list[Path]:
    files = sorted(DOCS.glob("*.md")) + [ROOT / "README.md"]
    for room in (*PACKAGE_ROOMS, "bench", "tests"):
        files += sorted(p for p in (ROOT / room).rglob("*") if p.suffix in (".py", ".md"))
    return [p for p in files if p.resolve() != Path(__file__).resolve()]


def test_nothing_points_at_the_specification_or_the_reading_list():
    found = [f"{p.relative_to(ROOT)}:{hit}" for p in _project_texts()
             for hit in stale_references(p.read_text(encoding="utf-8", errors="replace"))]
    assert found == []


@pytest.mark.parametrize("line", [
    "Register map: `../shared/spec/panel.md`.",
    '"""The operator panel (spec/panel.md)."""',
    "# contract: spec/cli.md",
    "(seed 004_07a64cf98683a8da.txt)",
    "AT960 (seed 003): 15 um",
    "the seed's method (Lin et al. 2023, `seeds/001`)",
])
def test_the_pointer_check_catches_a_specification_path_or_a_reading_list_number(line):
    assert stale_references(f"first line\n{line}\n")


@pytest.mark.parametrize("line", [
    "see docs/panel.md and docs/cli.md",
    "test data in ../shared/data/dlr-agile-justin",
    "--seed 3, over 10 + 10 seeds, seed 9 of compliance",
])
def test_the_pointer_check_leaves_docs_data_and_random_seeds_alone(line):
    assert stale_references(line) == []


def test_links_between_the_pages_resolve():
    for page in [*DOCS.glob("*.md"), README]:
        for target in re.findall(r"\]\(([^)#:]+\.md)(?:#[^)]*)?\)", page.read_text(encoding="utf-8")):
            assert (page.parent / target).is_file(), f"{page.name} links to {target}, which does not exist"


# -- the robot models page: every shipped file, with its source -------------------------------------------------------


def test_robot_models_page_lists_every_shipped_file_with_its_source():
    """docs/robot-models.md's table names exactly the files of config/robots/, each with a source, and each file
    opens with its header comment (where the numbers come from)."""
    from cellcal.config.robot_files import shipped_robots

    rows = table_under((DOCS / "robot-models.md").read_text(encoding="utf-8"), "# Robot model files")
    names = [_code(r["name"]) for r in rows]
    assert sorted(names) == sorted(shipped_robots()), "the table and config/robots/ differ"
    assert all(r["source of the nominal values"].strip() for r in rows), "a row without a source"
    for name, path in shipped_robots().items():
        assert path.read_text(encoding="utf-8").startswith("# "), f"{path.name}: no header comment naming its source"
