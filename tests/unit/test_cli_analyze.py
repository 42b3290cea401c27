"""`cellcal analyze`, `sim-data` and `import` as the command-line contract says."""
import json

import pytest

from cellcal.cli.main import main
from support.cli_run import run_cli  # tests/support/cli_run.py


@pytest.fixture(scope="module")
def backlash_csv(tmp_path_factory):
    path = tmp_path_factory.mktemp("sim") / "backlash.csv"
    assert main(["sim-data", "--robot", "ur5e", "--poses", "150", "--effect", "backlash:3", "--rms-mm", "0.3",
                 "--seed", "4", "-o", str(path)]) == 0
    return path


def test_analyze_json_has_every_key_the_contract_names(backlash_csv, tmp_path, capsys):
    code, out, err = run_cli(capsys, "analyze", "--robot", "ur5e", "--data", str(backlash_csv), "--json",
                             "--report", str(tmp_path / "report"))
    assert code == 0
    doc = json.loads(out)
    assert {"cause", "where", "magnitude", "baseline", "extended", "gain_pct", "candidates", "seconds"} <= set(doc)
    assert doc["cause"] == "backlash" and doc["where"] == {"joint": 3}
    truth = json.loads((backlash_csv.parent / "backlash.csv.truth.json").read_text())
    assert doc["magnitude"]["backlash_deg"] == pytest.approx(abs(truth["backlash"]["size"]) * 57.29578, rel=0.2)
    assert doc["extended"]["heldout_mean_mm"] < 0.6 * doc["baseline"]["heldout_mean_mm"]
    assert all({"cause", "heldout_mean_mm"} <= set(c) for c in doc["candidates"])
    for name in ("residual_vs_regressor.png", "heldout_histogram.png", "candidates.png", "report.html"):
        assert (tmp_path / "report" / name).stat().st_size > 1000
    assert "backlash" in (tmp_path / "report" / "report.md").read_text()
    assert "scored" in err  # progress on stderr


def test_analyze_says_none_on_clean_data(tmp_path, capsys):
    path = tmp_path / "clean.csv"
    assert main(["sim-data", "--robot", "ur5e", "--poses", "150", "--seed", "5", "-o", str(path)]) == 0
    code, out, _ = run_cli(capsys, "analyze", "--robot", "ur5e", "--data", str(path))
    assert code == 0 and "finding: none" in out


def test_analyze_refuses_bad_input_with_one_message(backlash_csv, tmp_path, capsys):
    code, out, err = run_cli(capsys, "analyze", "--robot", "ur10e", "--data", str(tmp_path / "missing.csv"))
    assert code == 2 and out == "" and "missing.csv" in err
    small = tmp_path / "small.csv"
    small.write_text("\n".join(backlash_csv.read_text().splitlines()[:12]) + "\n")
    code, out, err = run_cli(capsys, "analyze", "--robot", "ur5e", "--data", str(small))
    assert code == 2 and "at least 30" in err
    code, _, err = run_cli(capsys, "sim-data", "--effect", "gravity:2", "-o", str(tmp_path / "x.csv"))
    assert code == 2 and "gravity" in err


def test_import_refuses_an_unknown_layout(tmp_path, capsys):
    src = tmp_path / "export.csv"
    src.write_text("x,y\n1,2\n")
    code, out, err = run_cli(capsys, "import", "dlr-justin", str(src), "-o", str(tmp_path / "out.csv"))
    assert code == 2 and "export.csv" in err and not (tmp_path / "out.csv").exists()


def test_analyze_takes_a_robust_loss_as_identify_does(backlash_csv, tmp_path, capsys):
    lines = backlash_csv.read_text().splitlines()
    header = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    names = lines[header].split(",")
    x = names.index("x_mm")
    for i in range(header + 1, len(lines), 20):  # every 20th measurement 5 mm off: gross outliers
        cells = lines[i].split(",")
        cells[x] = repr(float(cells[x]) + 5.0)
        lines[i] = ",".join(cells)
    spoiled = tmp_path / "outliers.csv"
    spoiled.write_text("\n".join(lines) + "\n")
    code, out, _ = run_cli(capsys, "analyze", "--robot", "ur5e", "--data", str(spoiled), "--loss", "cauchy", "--json")
    doc = json.loads(out)
    assert code == 0 and doc["cause"] == "backlash" and doc["where"] == {"joint": 3}
    assert doc["heldout_trimmed_pct"] == 10.0
    with pytest.raises(SystemExit) as bad:
        main(["analyze", "--robot", "ur5e", "--data", str(spoiled), "--loss", "l7"])
    assert bad.value.code == 2 and "--loss" in capsys.readouterr().err
