"""The measurement CSV: what it reads, what it refuses and how it says so."""
import os

import numpy as np
import pytest

from cellcal.measurements.reader import read_measurements
from cellcal.measurements.table import DatasetError, MeasurementTable
from cellcal.measurements.writer import write_measurements, write_table
from cellcal.solvers.identification.measurement_model import Observations

Q6_RAD = "q1_rad,q2_rad,q3_rad,q4_rad,q5_rad,q6_rad"
Q6_DEG = "q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg"
ROW = "0.1,0.2,0.3,0.4,0.5,0.6,100.0,200.0,300.0"


def write(tmp_path, text, name="cal.csv"):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def refused(path, n_joints, line, *fragments):
    """Read must fail with one message starting 'path:line:' and holding every fragment."""
    with pytest.raises(DatasetError) as err:
        read_measurements(path, n_joints)
    message = str(err.value)
    prefix = f"{path}:{line}: " if line is not None else f"{path}: "
    assert message.startswith(prefix), message
    for fragment in fragments:
        assert fragment in message, message
    return message


# --- what it reads -------------------------------------------------------------------


def test_spec_example_parses(tmp_path):
    path = write(tmp_path, "# UR10e, tracker AT960, SMR on tool flange\n"
                 "q1_rad,q2_rad,q3_rad,q4_rad,q5_rad,q6_rad,x_mm,y_mm,z_mm,t_s,temp_c\n"
                 "0.1021,-1.2030,1.5544,-0.3512,1.5708,0.0000,1834.2213,-412.0871,903.5520,0.0,21.4\n")
    table = read_measurements(path, 6)
    assert len(table) == 1
    np.testing.assert_allclose(table.q_rad[0], [0.1021, -1.2030, 1.5544, -0.3512, 1.5708, 0.0], atol=1e-12)
    np.testing.assert_allclose(table.xyz_mm[0], [1834.2213, -412.0871, 903.5520], atol=1e-9)
    assert table.t_s.tolist() == [0.0] and table.temp_c.tolist() == [21.4]
    assert table.joint_unit == "rad" and table.target_names == ("tcp",) and table.target.tolist() == [0]
    assert table.quat is None and table.payload_kg is None and table.split is None
    assert table.line.tolist() == [3] and table.extra == {}


def test_degrees_are_converted_to_radians(tmp_path):
    path = write(tmp_path, f"{Q6_DEG},x_mm,y_mm,z_mm\n90,-45,180,0,30,-90,1,2,3\n")
    table = read_measurements(path, 6)
    assert table.joint_unit == "deg"
    np.testing.assert_allclose(table.q_rad[0], np.pi * np.array([0.5, -0.25, 1, 0, 1 / 6, -0.5]), atol=1e-15)


def test_target_names_are_in_order_of_first_appearance(tmp_path):
    rows = "".join(f"{ROW},{t}\n" for t in ["right", "left", "right", "smr2", "left"])
    table = read_measurements(write(tmp_path, f"{Q6_RAD},x_mm,y_mm,z_mm,target\n{rows}"), 6)
    assert table.target_names == ("right", "left", "smr2")
    assert table.target.tolist() == [0, 1, 0, 2, 1]


def test_unknown_columns_are_kept_as_text(tmp_path):
    path = write(tmp_path, f"{Q6_RAD},x_mm,y_mm,z_mm,operator,pose_id\n{ROW},anna,007\n{ROW},,8\n")
    table = read_measurements(path, 6)
    assert table.extra == {"operator": ("anna", ""), "pose_id": ("007", "8")}


def test_line_numbers_count_comments_and_blank_lines(tmp_path):
    path = write(tmp_path, f"# cell 3\n\n{Q6_RAD},x_mm,y_mm,z_mm\n{ROW}\n# pause\n\n{ROW}\n")
    assert read_measurements(path, 6).line.tolist() == [4, 7]


def test_quaternion_is_normalised(tmp_path):
    path = write(tmp_path, f"{Q6_RAD},x_mm,y_mm,z_mm,qw,qx,qy,qz\n{ROW},2,0,0,0\n{ROW},1,1,1,1\n")
    np.testing.assert_allclose(read_measurements(path, 6).quat, [[1, 0, 0, 0], [0.5, 0.5, 0.5, 0.5]], atol=1e-15)


def test_crlf_line_ends_bom_and_padded_header_are_read(tmp_path):
    path = tmp_path / "cal.csv"
    path.write_bytes(("\ufeff" + " q1_rad, q2_rad ,x_mm,y_mm,z_mm\r\n0.5, 1.5,1,2,3\r\n").encode("utf-8"))
    table = read_measurements(path, 2)
    assert table.q_rad.tolist() == [[0.5, 1.5]] and table.line.tolist() == [2]


def test_rows_subset_keeps_every_field_and_the_target_names(tmp_path):
    rows = "".join(f"{ROW},{t},{s},r{i}\n" for i, (t, s) in enumerate(zip("abab", ["cal", "val", "cal", "val"])))
    table = read_measurements(write(tmp_path, f"{Q6_RAD},x_mm,y_mm,z_mm,target,split,note\n{rows}"), 6)
    val = table.rows(table.split == "val")
    assert len(val) == 2 and val.line.tolist() == [3, 5] and val.extra == {"note": ("r1", "r3")}
    assert val.target_names == ("a", "b") and val.target.tolist() == [1, 1]
    assert table.rows([2]).split.tolist() == ["cal"]


def test_observations_carry_radians_millimetres_and_targets(tmp_path):
    table = read_measurements(write(tmp_path, f"{Q6_RAD},x_mm,y_mm,z_mm,target\n{ROW},left\n"), 6)
    obs = table.observations()
    assert isinstance(obs, Observations)
    assert obs.q is table.q_rad and obs.xyz_mm is table.xyz_mm and obs.target_names == ("left",)


def _random_table(seed=4, n=25):
    rng = np.random.default_rng(seed)
    quat = rng.normal(size=(n, 4))
    return dict(
        q_rad=rng.uniform(-np.pi, np.pi, size=(n, 6)),
        xyz_mm=rng.uniform(-2500, 2500, size=(n, 3)),
        target_names=("right", "left, outer"),
        target=rng.integers(0, 2, size=n),
        t_s=np.cumsum(rng.uniform(0.5, 3.0, size=n)),
        temp_c=rng.uniform(19, 26, size=n),
        payload_kg=rng.choice([0.0, 2.5, 10.0], size=n),
        split=rng.choice(["cal", "val"], size=n),
        quat=quat / np.linalg.norm(quat, axis=1, keepdims=True),
    )


@pytest.mark.parametrize("joint_unit", ["rad", "deg"])
def test_round_trip_reproduces_values_within_1e_9(tmp_path, joint_unit):
    x = _random_table()
    path = tmp_path / "rt.csv"
    write_measurements(path, **x, comment="cell 3\ntracker AT960", joint_unit=joint_unit)
    assert path.read_text().startswith("# cell 3\n# tracker AT960\n")
    table = read_measurements(path, 6)
    assert table.joint_unit == joint_unit
    for key in ("q_rad", "xyz_mm", "t_s", "temp_c", "payload_kg", "quat"):
        np.testing.assert_allclose(getattr(table, key), x[key], rtol=0, atol=1e-9, err_msg=key)
    assert [table.target_names[i] for i in table.target] == [x["target_names"][i] for i in x["target"]]
    assert table.split.tolist() == x["split"].tolist()


def test_write_table_round_trips_a_read_table_with_its_extra_columns(tmp_path):
    path = tmp_path / "a.csv"
    write_measurements(path, q_rad=np.full((3, 2), 0.25), xyz_mm=np.arange(9.0).reshape(3, 3), joint_unit="deg")
    first = read_measurements(path, 2)
    first = MeasurementTable(**{**first.__dict__, "extra": {"note": ("a", "b,c", "")}})
    write_table(tmp_path / "b.csv", first, comment="copy")
    again = read_measurements(tmp_path / "b.csv", 2)
    assert "target" not in (tmp_path / "b.csv").read_text()
    np.testing.assert_allclose(again.q_rad, first.q_rad, rtol=0, atol=1e-9)
    assert again.xyz_mm.tolist() == first.xyz_mm.tolist()
    assert again.extra == first.extra and again.joint_unit == "deg" and again.target_names == ("tcp",)


# --- what it refuses, and how it says so --------------------------------------------


def test_missing_required_column_is_named_with_the_columns_this_robot_needs(tmp_path):
    path = write(tmp_path, f"# comment\n{Q6_RAD},x_mm,z_mm\n0.1,0.2,0.3,0.4,0.5,0.6,1,3\n")
    message = refused(path, 6, 2, "missing required column 'y_mm'")
    assert "6-joint robot needs q1_rad .. q6_rad" in message and "x_mm, y_mm, z_mm" in message


def test_too_many_joint_columns_names_both_joint_counts(tmp_path):
    path = write(tmp_path, f"{Q6_RAD},q7_rad,x_mm,y_mm,z_mm\n{ROW},0.7\n")
    refused(path, 6, 1, "column 'q7_rad'", "q7", "6 joints")


def test_too_few_joint_columns_names_the_missing_joint_and_both_counts(tmp_path):
    path = write(tmp_path, "q1_rad,q2_rad,q3_rad,q4_rad,q5_rad,x_mm,y_mm,z_mm\n0.1,0.2,0.3,0.4,0.5,1,2,3\n")
    refused(path, 6, 1, "missing required column 'q6_rad'", "5 joint columns", "6 joints")


def test_zero_based_joint_numbering_is_refused_naming_the_column(tmp_path):
    path = write(tmp_path, "q0_rad,q1_rad,x_mm,y_mm,z_mm\n0.1,0.2,1,2,3\n")
    refused(path, 2, 1, "column 'q0_rad'")


def test_non_numeric_value_is_refused_naming_line_and_column(tmp_path):
    path = write(tmp_path, f"{Q6_RAD},x_mm,y_mm,z_mm\n{ROW}\n0.1,0.2,0.3,0.4,0.5,0.6,1,abc,3\n")
    message = refused(path, 6, 3, "column 'y_mm'", "'abc' is not a number")
    assert message == f"{path}:3: column 'y_mm': 'abc' is not a number"


@pytest.mark.parametrize("text", ["", "1_000", "1.5.2", "0x10"])
def test_malformed_numbers_are_refused(tmp_path, text):
    path = write(tmp_path, f"{Q6_RAD},x_mm,y_mm,z_mm\n{ROW}\n{ROW.replace('300.0', text)}\n")
    refused(path, 6, 3, "column 'z_mm'", "is not a number")


@pytest.mark.parametrize("text", ["nan", "NaN", "inf", "-inf", "1e999"])
def test_non_finite_values_are_refused_naming_line_and_column(tmp_path, text):
    path = write(tmp_path, f"{Q6_RAD},x_mm,y_mm,z_mm,t_s\n{ROW},0\n\n{ROW},{text}\n")
    refused(path, 6, 4, "column 't_s'", f"'{text}' is not finite")


def test_mixed_joint_units_are_refused_naming_the_column(tmp_path):
    path = write(tmp_path, "q1_deg,q2_rad,x_mm,y_mm,z_mm\n10,0.2,1,2,3\n")
    refused(path, 2, 1, "column 'q2_rad'", "mixed joint units")


def test_duplicate_header_name_is_refused_naming_the_column(tmp_path):
    path = write(tmp_path, f"{Q6_RAD},x_mm,y_mm,z_mm,x_mm\n{ROW},1\n")
    refused(path, 6, 1, "column 'x_mm'", "duplicate header name")


def test_empty_file_is_refused(tmp_path):
    refused(write(tmp_path, ""), 6, None, "empty file")


def test_file_of_only_comments_and_blank_lines_is_refused_as_empty(tmp_path):
    refused(write(tmp_path, "# nothing measured\n\n   \n"), 6, None, "empty file")


def test_header_without_rows_is_refused(tmp_path):
    refused(write(tmp_path, f"# c\n{Q6_RAD},x_mm,y_mm,z_mm\n# no rows yet\n"), 6, 2, "no measurement rows")


@pytest.mark.parametrize("row", [ROW + ",9", ROW.rsplit(",", 1)[0]])
def test_row_with_wrong_number_of_fields_is_refused_naming_the_line(tmp_path, row):
    path = write(tmp_path, f"{Q6_RAD},x_mm,y_mm,z_mm\n{ROW}\n{ROW}\n{row}\n")
    refused(path, 6, 4, "fields, header has 9")


def test_split_other_than_cal_or_val_is_refused_naming_the_column(tmp_path):
    path = write(tmp_path, f"{Q6_RAD},x_mm,y_mm,z_mm,split\n{ROW},cal\n{ROW},test\n")
    refused(path, 6, 3, "column 'split'", "'test'")


def test_partial_quaternion_is_refused_naming_the_missing_column(tmp_path):
    path = write(tmp_path, f"{Q6_RAD},x_mm,y_mm,z_mm,qw,qx,qy\n{ROW},1,0,0\n")
    refused(path, 6, 1, "column 'qz'", "partial quaternion")


def test_zero_norm_quaternion_is_refused_naming_line_and_columns(tmp_path):
    path = write(tmp_path, f"{Q6_RAD},x_mm,y_mm,z_mm,qw,qx,qy,qz\n{ROW},1,0,0,0\n{ROW},0,0,0,0\n")
    refused(path, 6, 3, "'qw'", "'qz'", "zero norm")


def test_empty_target_id_is_refused_naming_line_and_column(tmp_path):
    path = write(tmp_path, f"{Q6_RAD},x_mm,y_mm,z_mm,target\n{ROW},left\n{ROW},  \n")
    refused(path, 6, 3, "column 'target'", "empty target id")


def test_missing_file_is_refused_naming_it(tmp_path):
    refused(tmp_path / "absent.csv", 6, None, "cannot read file")


def test_unreadable_path_is_refused_naming_it(tmp_path):
    os.mkdir(tmp_path / "dir.csv")
    refused(tmp_path / "dir.csv", 6, None, "cannot read file")


def test_non_utf8_file_is_refused_naming_the_line(tmp_path):
    path = tmp_path / "cal.csv"
    path.write_bytes(f"{Q6_RAD},x_mm,y_mm,z_mm,target\n{ROW},a\n{ROW},".encode() + b"l\xe9ft\n")
    refused(path, 6, 3, "not UTF-8")


def test_error_in_the_last_row_refuses_the_whole_file(tmp_path):
    rows = f"{ROW}\n" * 50 + "0.1,0.2,0.3,0.4,0.5,0.6,1,2,inf\n"
    refused(write(tmp_path, f"{Q6_RAD},x_mm,y_mm,z_mm\n{rows}"), 6, 52, "column 'z_mm'")
