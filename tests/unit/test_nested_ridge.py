"""Choices made inside each fold's training rows: the prior weight of an effect's parameters
(``crossval.ridge_steps``: nothing of a fold decides its own weight, the weight helps where the
training rows barely see some directions, and costs nothing where they see every one), and the
inner score the baseline's variant is chosen by for each fold (``FoldFactors.inner_sse``)."""
import numpy as np

from cellcal.solvers.estimation import crossval

NOISE_MEAN = np.sqrt(8.0 / np.pi)  # mean length of 3-D noise of standard deviation 1 per coordinate


def problem(seed: int, hidden: bool, n: int = 400, p_geometry: int = 6, p_effect: int = 30):
    """Rows of 3 coordinates, noise 1: well-seen geometry columns and effect columns, the last
    half of which differ from one another by 1e-4 of a column's size on every row but 3% of them.
    hidden: those 3% lie at five configurations, so whole neighbour groups of them go to the folds and
    a fold's training may barely see the differences (as a tree's rarely moved place); else no column
    is weak."""
    rng = np.random.default_rng(seed)
    j = rng.normal(size=(n, 3, p_geometry + p_effect))
    q = rng.uniform(-3, 3, size=(n, 6))  # distinct configurations: one row a neighbour group
    if hidden:
        strong = rng.uniform(size=n) < 0.03
        lever = np.where(strong, 1.0, 1e-4)
        half = p_geometry + p_effect // 2
        j[:, :, half:] = j[:, :, half:half + 1] + lever[:, None, None] * rng.normal(size=(n, 3, p_effect - p_effect // 2))
        at = np.flatnonzero(strong)
        q[at] = q[at[np.arange(len(at)) % 5]]  # five configurations: the folds each hold about one
    theta = np.r_[np.zeros(p_geometry), rng.normal(size=p_effect)]
    r = -(j @ theta) + rng.normal(size=(n, 3))  # the residual at zero: predicted - measured
    folds = crossval.fold_ids(q, 5, seed=seed)
    if hidden and seed < 2:
        # the five configurations dealt unevenly on purpose, three of them to fold 0 (as a draw of folds may
        # deal a tree's rarely moved place): fold 0's training sees the differences at two configurations only
        at = np.flatnonzero(strong)
        uneven = np.asarray(folds).copy()
        for c in range(3):
            uneven[at[np.arange(len(at)) % 5 == c]] = 0
        sub = folds.sub
        folds = uneven.view(crossval.FoldIds)
        folds.sub = sub
    return j, r, folds, p_geometry, p_effect


def factors_of(j, r, folds):
    f = crossval.FoldFactors(folds, j.shape[2])
    f.add(slice(0, len(r)), j, r)
    return f


def heldout_mean(j, r, folds, steps):
    return float(crossval.heldout_errors([(slice(0, len(r)), j)], r, factors_of(j, r, folds), steps)[0].mean())


def ridge(j, r, folds, p_g, p_e):
    p = p_g + p_e
    return crossval.ridge_steps(factors_of(j, r, folds), np.arange(p), np.arange(p) >= p_g, np.zeros(p))


def test_a_fold_s_own_rows_never_decide_its_weight():
    j, r, folds, p_g, p_e = problem(0, hidden=True)
    _, chosen = ridge(j, r, folds, p_g, p_e)
    for k in range(5):  # whatever fold k's own rows say, its weight is what its training rows chose
        r2 = r.copy()
        mine = np.asarray(folds) == k
        r2[mine] = np.random.default_rng(10 + k).normal(scale=50.0, size=(int(mine.sum()), 3))
        assert ridge(j, r2, folds, p_g, p_e)[1][k] == chosen[k]


def test_the_weight_helps_where_directions_are_barely_seen_and_costs_nothing_where_all_are():
    helped = []
    for seed in range(6):
        for hidden in (True, False):
            j, r, folds, p_g, p_e = problem(seed, hidden)
            plain = heldout_mean(j, r, folds, factors_of(j, r, folds).steps(np.arange(p_g + p_e)))
            steps, chosen = ridge(j, r, folds, p_g, p_e)
            weighed = heldout_mean(j, r, folds, steps)
            if hidden:
                # where a fold's training holds few of the rows that see the differences (the five configurations
                # fall unevenly on the folds), its plain step scatters along them by up to ~1e4 / sqrt(rows)
                # noise units; weighed inside the folds, every held-out mean stays within twice the noise's 1.6
                assert weighed < 2 * NOISE_MEAN, (seed, plain, weighed, chosen)
                helped.append(plain / weighed)
            else:
                # every direction well seen (400 rows, 36 columns): the prior can only pull true parameters of
                # ~1 towards zero, and the inner folds choose a weight too small to matter: within 1% of the
                # plain step's held-out mean (its own scatter over seeds is ~3%)
                assert weighed <= 1.01 * plain, (seed, plain, weighed, chosen)
    # the seeds where the folds fall unevenly (0 and 1, on purpose): the plain step's held-out mean there is
    # several times the noise; weighed, it is the noise
    assert sum(h > 5 for h in helped) >= 1, helped


def test_the_inner_score_a_fold_chooses_by_is_its_training_rows_cross_validated_and_nothing_of_its_own():
    # FoldFactors.inner_sse, by which the baseline's variant is chosen for each fold: the held-out sum of
    # squares of fold k's training rows, each other fold's sub-folds held out in turn, straight from the rows
    j, r, folds, p_g, p_e = problem(1, hidden=False)
    f = factors_of(j, r, folds)
    fold, sub = np.asarray(folds), np.asarray(folds.sub)
    a, b = j.reshape(len(r), 3, -1), r
    for k in range(5):
        expected = 0.0
        for other in range(5):
            for s in np.unique(sub):
                held = (fold == other) & (sub == s)
                if other == k or not held.any():
                    continue
                train = (fold != k) & ~held
                x = np.linalg.lstsq(a[train].reshape(-1, a.shape[2]), -b[train].ravel(), rcond=None)[0]
                expected += float(np.sum((a[held].reshape(-1, a.shape[2]) @ x + b[held].ravel()) ** 2))
        # the same normal equations solved two ways: agreement to 1e-9 of the sum (condition ~10 here)
        assert abs(f.inner_sse(k) - expected) <= 1e-9 * expected
        r2 = r.copy()
        r2[fold == k] += 100.0  # fold k's own rows say anything at all: its inner score stays
        assert abs(factors_of(j, r2, folds).inner_sse(k) - f.inner_sse(k)) <= 1e-9 * expected
