"""``cellcal import mukca``: socket-plate seatings (one folder per placement, hole_<k>.csv of 7 joint angles) to the
point form of the measurement CSV; several sources in one file; and one held-out placement of the real data."""
import json
from pathlib import Path

import numpy as np
import pytest

from cellcal.cli.main import main
from cellcal.measurements.importers import mukca
from cellcal.measurements.reader import read_measurements
from cellcal.measurements.table import DatasetError

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "mukca-panda"
PLATE = Path(__file__).resolve().parents[2] / "bench" / "mukca_plate.yaml"


def placement(folder: Path, rows_per_hole: int, seed: int) -> dict:
    """A placement folder as the data set has it: hole_<k>.csv, the authors' hole_<k>_pose.csv, a comment file."""
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    q = {}
    for hole in ("hole_0", "hole_1"):
        q[hole] = rng.uniform(-2, 2, (rows_per_hole, 7))
        np.savetxt(folder / f"{hole}.csv", q[hole], delimiter=",", fmt="%.18e")
        np.savetxt(folder / f"{hole}_pose.csv", rng.uniform(-1, 1, (rows_per_hole, 7)), delimiter=",")
    (folder / "comments.txt").write_text("tool on centerline\n")
    return q


def test_a_folder_of_placements_gives_one_setup_per_folder_bit_for_bit(tmp_path):
    a = placement(tmp_path / "robot" / "left", 3, seed=1)
    b = placement(tmp_path / "robot" / "right", 2, seed=2)
    out = tmp_path / "all.csv"
    assert main(["import", "mukca", str(tmp_path / "robot"), "-o", str(out)]) == 0
    table = read_measurements(out, 7)
    assert list(table.setup) == ["left"] * 6 + ["right"] * 4
    assert list(table.point) == ["hole_0"] * 3 + ["hole_1"] * 3 + ["hole_0"] * 2 + ["hole_1"] * 2
    # the joint values round-trip exactly (shortest repr of the same doubles): pose files are not read
    np.testing.assert_array_equal(table.q_rad, np.vstack([a["hole_0"], a["hole_1"], b["hole_0"], b["hole_1"]]))


def test_one_placement_folder_and_several_sources(tmp_path):
    placement(tmp_path / "r" / "front", 2, seed=3)
    placement(tmp_path / "r" / "back", 2, seed=4)
    one = mukca(tmp_path / "r" / "front")
    assert set(one["setup"]) == {"front"} and len(one["q_rad"]) == 4
    out = tmp_path / "two.csv"
    assert main(["import", "mukca", str(tmp_path / "r" / "front"), str(tmp_path / "r" / "back"), "-o", str(out)]) == 0
    assert list(dict.fromkeys(read_measurements(out, 7).setup)) == ["front", "back"]  # in the order given


def test_the_same_placement_twice_is_refused(tmp_path, capsys):
    placement(tmp_path / "front", 2, seed=5)
    code = main(["import", "mukca", str(tmp_path / "front"), str(tmp_path / "front"), "-o", str(tmp_path / "x.csv")])
    assert code == 2 and "setup 'front' is also in" in capsys.readouterr().err
    assert not (tmp_path / "x.csv").exists()


def test_a_short_row_and_an_empty_folder_are_refused_naming_the_file(tmp_path):
    (tmp_path / "p").mkdir()
    (tmp_path / "p" / "hole_0.csv").write_text("1,2,3,4,5,6,7\n1,2,3,4,5,6\n")
    with pytest.raises(DatasetError, match=r"hole_0.csv: record 2: .*expected 7 numbers, got 6"):
        mukca(tmp_path / "p")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="no hole_<k>.csv"):
        mukca(tmp_path / "empty")


@pytest.mark.skipif(not DATA.exists(), reason="shared data set not beside the repository")
def test_a_held_out_placement_of_the_real_panda(tmp_path, capsys):
    """panda_3 with 'backcenter' held out (bench/mukca_panda_folds.py runs every placement of both robots).
    The nominal Franka table leaves millimetres; the calibrated arm must return to the moved plate within
    0.35 mm on average: the accuracy asked of a joint-angles-only calibration at an unseen placement (the data
    set's authors report sub-millimetre there; at the plate's 0.1 mm distance tolerance and hand seating, a
    few tenths of a millimetre is what such data can support)."""
    robot = DATA / "panda_3"
    cal, val = tmp_path / "cal.csv", tmp_path / "val.csv"
    others = [str(p) for p in sorted(robot.iterdir()) if p.is_dir() and p.name != "backcenter"]
    assert main(["import", "mukca", *others, "-o", str(cal)]) == 0
    assert main(["import", "mukca", str(robot / "backcenter"), "-o", str(val)]) == 0
    capsys.readouterr()
    assert main(["identify", "--robot", "franka-panda", "--data", str(cal), "--fixture", str(PLATE),
                 "--validate", str(val), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["validate"]["new_setups"] == ["backcenter"]
    assert doc["before"]["validate_mean_mm"] > 1.0  # the nominal arm: millimetres (2.8 here), so the check is not void
    assert doc["validate"]["mean_mm"] <= 0.35
