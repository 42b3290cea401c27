"""Large files: the solvers work a block of rows at a time, and the answer must not depend on it.

Every product here is checked against the whole-matrix computation it replaces (to 1e-9
relative): R factors against the full QR, the Levenberg-Marquardt fit against scipy's,
identify and analyze with blocks of a few rows against one block holding every row. Speed
and memory are the bench's (bench/large_input_bench.py), not the suite's.
"""
import numpy as np
import pytest
from scipy.optimize import least_squares

from cellcal.config.robot_files import load_robot
from cellcal.measurements.reader import read_measurements
from cellcal.measurements.table import DatasetError
from cellcal.sims.physics.kinematic_arm import SimulatedArm
from cellcal.sims.physics.physical_arm import HiddenEffect
from cellcal.sims.physics.workspace import full_workspace
from cellcal.solvers.estimation import crossval, lsq
from cellcal.solvers.analysis.analyze import analyze
from cellcal.solvers.analysis.effects import JointBasis, approach_directions
from cellcal.solvers.identification.identify import IdentifyOptions, fit, identify, initial_base_and_targets, scales
from cellcal.solvers.identification.measurement_model import Layout, jacobian, predict

from support.hidden_cases import make_case


@pytest.fixture(scope="module")
def campaign():
    model = load_robot("abb-irb4600")
    rng = np.random.default_rng(5)
    arm = SimulatedArm(model, rng)
    return model, arm.measure(full_workspace(model, 200, rng))


def test_r_factor_of_row_blocks_is_the_r_factor_of_the_whole_matrix():
    a = np.random.default_rng(0).normal(size=(1000, 12)) * np.logspace(-3, 3, 12)
    acc = lsq.RFactor(12)
    for rows in lsq.chunks(len(a), 77):
        acc.add(a[rows])
    np.testing.assert_allclose(acc.r.T @ acc.r, a.T @ a, rtol=1e-9, atol=1e-9 * np.abs(a.T @ a).max())
    s = np.linalg.svd(a, compute_uv=False)
    # a backward-stable QR and SVD leave every singular value good to ~n eps |a| (Weyl), small ones included:
    # the smallest is 1e-6 of |a| here, so 1e-9 relative on it would be ~5 eps |a|, within a kernel's rounding
    np.testing.assert_allclose(np.linalg.svd(acc.r, compute_uv=False), s, rtol=0,
                               atol=a.shape[1] * np.finfo(float).eps * s[0])


def test_held_out_errors_from_fold_factors_equal_a_direct_solve_per_fold():
    rng = np.random.default_rng(1)
    j, r = rng.normal(size=(300, 3, 5)), rng.normal(size=(300, 3))
    folds = rng.integers(0, 4, 300)
    got = crossval.one_step_heldout(j, r, folds, penalty=np.ones(5), deviation=rng.normal(size=5), lams=(0.0,))[0]
    want = np.empty(300)
    for f in range(4):
        train, held = folds != f, folds == f
        step = np.linalg.lstsq(j[train].reshape(-1, 5), -r[train].ravel(), rcond=None)[0]
        want[held] = np.linalg.norm(r[held] + j[held] @ step, axis=1)
    np.testing.assert_allclose(got, want, rtol=1e-9)


@pytest.mark.parametrize("loss", ["linear", "soft_l1"])
def test_levenberg_marquardt_on_normal_equations_finds_scipys_minimum(campaign, loss):
    model, obs = campaign
    layout = Layout(model, obs.target_names)
    x0 = initial_base_and_targets(layout, obs)
    free = np.ones(layout.size, bool)
    free[[model.index(n) for n in ("theta1", "d1", "d2", "theta6", "d6", "a6", "alpha6")]] = False
    scale = scales(layout, x0, obs)
    ours = fit(layout, obs, x0, free, scale=scale, loss=loss, f_scale=0.2)

    def unpack(z):
        x = x0.copy()
        x[free] = z
        return x

    theirs = least_squares(lambda z: (predict(layout, unpack(z), obs) - obs.xyz_mm).ravel(), x0[free],
                           jac=lambda z: jacobian(layout, unpack(z), obs)[1].reshape(-1, layout.size)[:, free],
                           method="lm" if loss == "linear" else "trf", x_scale=scale[free], xtol=1e-12, ftol=1e-12,
                           gtol=1e-12, **({} if loss == "linear" else {"loss": loss, "f_scale": 0.2}))
    assert ours.status > 0 and theirs.status > 0
    # the same minimum: no higher a cost, and every unknown (in length units: mm, or rad over the reach; the
    # estimates' own uncertainty is ~1e-2) as close as the stopping rule determines it: each fit may stop once
    # a step gains less than ftol = 1e-12 of the cost, i.e. up to ftol * cost above the minimum, where the
    # scaled x can still be sqrt(2 ftol cost) / s_min(J) off in its weakest direction (~4e-6 each here; the
    # two have been seen 1e-10 to 7e-7 apart, depending on the BLAS kernel)
    s_min = np.linalg.svd(jacobian(layout, ours.x, obs)[1].reshape(-1, layout.size)[:, free] * scale[free],
                          compute_uv=False)[-1]
    np.testing.assert_allclose(ours.x[free] / scale[free], theirs.x / scale[free], rtol=0,
                               atol=2 * np.sqrt(2 * 1e-12 * theirs.cost) / s_min)
    ours_r = (predict(layout, ours.x, obs) - obs.xyz_mm).ravel()
    rho = (lambda r: r @ r) if loss == "linear" else (lambda r: 2 * np.sum(np.sqrt(1 + (r / 0.2) ** 2) - 1))
    drho = (lambda r: 2 * r) if loss == "linear" else (lambda r: 2 * r / 0.2**2 / np.sqrt(1 + (r / 0.2) ** 2))
    # "no higher" to what the cost can resolve: each fit stops within ftol * cost (~2e-12) of the minimum, below
    # the cost's own rounding: each residual is a difference of positions of up to |xyz| mm through a chain of
    # 4x4 products, good to ~16 eps |xyz| and rounded differently by each BLAS kernel, so rho is good to
    # |rho'(r)| sqrt(N) 16 eps |xyz| (~5e-10 relative here; kernels have put the two 1.3e-12 apart)
    eps_r = 16 * np.finfo(float).eps * np.abs(obs.xyz_mm).max()
    assert rho(ours_r) <= rho(theirs.fun) + np.linalg.norm(drho(ours_r)) * np.sqrt(ours_r.size) * eps_r


def test_identify_does_not_depend_on_the_block_size(campaign, monkeypatch):
    model, obs = campaign
    whole = identify(model, obs, IdentifyOptions(regularize="cv"))
    monkeypatch.setattr(lsq, "CHUNK_ROWS", 37)
    blocks = identify(model, obs, IdentifyOptions(regularize="cv"))
    assert np.array_equal(whole.free, blocks.free) and whole.lam == blocks.lam
    np.testing.assert_allclose(blocks.x, whole.x, rtol=0, atol=1e-9 * np.abs(whole.x).max())
    np.testing.assert_allclose(blocks.std, whole.std, rtol=1e-6)
    np.testing.assert_allclose([e for _, e in blocks.cv_curve], [e for _, e in whole.cv_curve], rtol=1e-9)


def test_analyze_does_not_depend_on_the_block_size(monkeypatch):
    model = load_robot("ur10e")
    case = make_case(model, [HiddenEffect("backlash", 2)], [4.0], n=240, seed=2)
    ctx = case.campaign.ctx
    whole = analyze(model, case.campaign.obs, ctx)
    monkeypatch.setattr(lsq, "CHUNK_ROWS", 50)
    blocks = analyze(model, case.campaign.obs, ctx)
    assert (blocks.cause, blocks.where) == (whole.cause, whole.where) == ("backlash", {"joint": 3})
    assert [c.label for c in blocks.candidates] == [c.label for c in whole.candidates]
    np.testing.assert_allclose([c.heldout_mean_mm for c in blocks.candidates],
                               [c.heldout_mean_mm for c in whole.candidates], rtol=1e-9)
    np.testing.assert_allclose(blocks.extended.heldout_errors, whole.extended.heldout_errors, rtol=1e-7)


def test_a_compact_joint_basis_is_the_dense_one():
    rng = np.random.default_rng(3)
    single = JointBasis.single(rng.normal(size=(40, 2)), 1, 6)
    dense = np.zeros((40, 6, 2))
    dense[:, 1, :] = single.values
    both = JointBasis.side_by_side([(single, 2), (None, 1), (JointBasis.dense_array(dense), 2)], 40, 6)
    np.testing.assert_array_equal(np.asarray(single), dense)
    jq = rng.normal(size=(40, 3, 6))
    np.testing.assert_allclose(both.columns(jq), np.einsum("nij,njm->nim", jq, np.asarray(both)), rtol=1e-12)
    np.testing.assert_allclose(both.delta(np.arange(5.0)), np.asarray(both) @ np.arange(5.0), rtol=1e-12)
    np.testing.assert_array_equal(np.asarray(both[[3, 7]]), np.asarray(both)[[3, 7]])


def test_approach_directions_carry_the_last_change_of_each_joint():
    q = np.array([[0.0, 1.0], [0.1, 1.0], [0.1, 0.9], [0.1, 0.9], [0.05, 0.95]])
    np.testing.assert_array_equal(approach_directions(q), [[0, 0], [1, 0], [1, -1], [1, -1], [-1, 1]])


ROW = "0.1,0.2,0.3,0.4,0.5,0.6,100.0,200.0,300.0"


def test_problems_are_reported_in_column_order_whatever_block_they_fall_in(tmp_path, monkeypatch):
    import cellcal.measurements.reader as dataset

    monkeypatch.setattr(dataset, "_BLOCK_ROWS", 2)
    rows = [ROW] * 6
    rows[1] = ROW.replace("200.0", "abc")  # y_mm, line 3: an earlier row, a later column
    rows[4] = ROW.replace("0.3", "1e999", 1)  # q3_rad, line 6: reported first
    path = tmp_path / "cal.csv"
    path.write_text("q1_rad,q2_rad,q3_rad,q4_rad,q5_rad,q6_rad,x_mm,y_mm,z_mm\n" + "\n".join(rows) + "\n")
    with pytest.raises(DatasetError) as err:
        read_measurements(path, 6)
    assert str(err.value) == f"{path}:6: column 'q3_rad': '1e999' is not finite"
    rows[4] = ROW.replace("100.0", "2e5")  # x_mm beyond 100 m, line 6: before y_mm's bad text
    path.write_text("q1_rad,q2_rad,q3_rad,q4_rad,q5_rad,q6_rad,x_mm,y_mm,z_mm\n" + "\n".join(rows) + "\n")
    with pytest.raises(DatasetError, match=r":6: column 'x_mm': 2e5 mm is not a position"):
        read_measurements(path, 6)


def test_quoted_and_plain_rows_read_alike(tmp_path, monkeypatch):
    import cellcal.measurements.reader as dataset

    monkeypatch.setattr(dataset, "_BLOCK_ROWS", 2)
    path = tmp_path / "cal.csv"
    path.write_text("q1_rad,q2_rad,q3_rad,q4_rad,q5_rad,q6_rad,x_mm,y_mm,z_mm,note\n"
                    f"{ROW},plain\n" + '"0.1",0.2,0.3,0.4,0.5,0.6,100.0," 200.0",300.0,"a, b"\n' + f"{ROW},\n")
    table = read_measurements(path, 6)
    np.testing.assert_array_equal(table.xyz_mm, [[100.0, 200.0, 300.0]] * 3)
    assert table.extra == {"note": ("plain", "a, b", "")} and table.line.tolist() == [2, 3, 4]


def test_neighbour_groups_found_block_by_block_are_the_connected_components_of_all_pairs(monkeypatch):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(4)
    # a log that lingers: runs of nearby configurations, some revisited later
    centres = rng.uniform(-1, 1, (40, 6))
    q = centres[rng.integers(0, 40, 3000)] + rng.normal(scale=0.01, size=(3000, 6))
    pairs = cKDTree(q).query_pairs(0.03, p=np.inf, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(3000, 3000))
    want = connected_components(graph, directed=False)[1]
    monkeypatch.setattr(crossval, "GROUP_BLOCK_ROWS", 128)
    got = crossval.groups(q, 0.03)
    assert 1 < want.max() < 2999  # neither one group nor all alone: the test means something
    np.testing.assert_array_equal(got, want)


def test_joint_velocity_columns_are_read_in_blocks_and_a_bad_value_is_named(tmp_path, monkeypatch):
    import cellcal.measurements.reader as dataset

    monkeypatch.setattr(dataset, "_BLOCK_ROWS", 2)
    header = "q1_rad,q2_rad,q3_rad,q4_rad,q5_rad,q6_rad,x_mm,y_mm,z_mm," + ",".join(f"dq{j}_deg_s" for j in range(1, 7))
    rows = [f"{ROW}," + ",".join(f"{10 * i + j}" for j in range(1, 7)) for i in range(5)]
    path = tmp_path / "trig.csv"
    path.write_text(header + "\n" + "\n".join(rows) + "\n")
    dq = dataset.joint_velocities(read_measurements(path, 6))
    np.testing.assert_allclose(dq, np.deg2rad([[10 * i + j for j in range(1, 7)] for i in range(5)]), rtol=1e-15)
    rows[3] = rows[3].replace(",34,", ",3.4.1,")
    path.write_text(header + "\n" + "\n".join(rows) + "\n")
    with pytest.raises(DatasetError) as err:
        dataset.joint_velocities(read_measurements(path, 6))
    assert str(err.value) == f"{path}:5: column 'dq4_deg_s': '3.4.1' is not a number"
