"""Grouped k-fold cross-validation on a linearised model.

Rows measured at the same or at neighbouring joint configurations carry nearly
the same information, so they go into one fold: held-out data must be data the
fit has not effectively seen. Each fold's estimate is one Gauss-Newton step from
a fit to all rows, using only the fold's training rows; near a least-squares
minimum (and the kinematics is very nearly linear over calibration-sized
changes) that step is the fold's own solution to second order.

The folds depend on the configurations alone, never on the order of the rows (``fold_ids``):
a finding must be the same for the same rows in any order. Each joint's extreme configurations
are dealt so that every fold's training keeps that joint's range (``range_keeping_deal``).

Data logged along a path (a tracker sampling a robot program: each row a degree or so from
the next) chain into one neighbour group. Such data (the largest group holds more than one
fold's share of the rows) are cut into blocks of neighbouring configurations instead
(``path_fold_ids``), whole blocks to a fold, and the rows of other folds that lie within the
neighbour radius of a fold's rows are left out of that fold's training (``FoldIds.exclude``):
the gap a neighbour needs, so the held-out block is data the fit has not effectively seen.

The Jacobian is never needed whole: per-fold R factors (``FoldFactors``) give every
fold's normal equations, and the held-out errors take one more pass over its rows.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from cellcal.solvers.estimation.lsq import RFactor, chunks, stacked_r


NEIGHBOUR_RAD = np.deg2rad(2.0)  # configurations this close carry nearly the same information: one fold


def groups(q: np.ndarray, radius_rad: float = 0.0) -> np.ndarray:
    """Group id per row: rows within radius_rad (max over joints) of each other are linked.

    Ids are numbered in order of each group's first row. The links are found a block of
    rows at a time and merged into the groups found so far, so a log that lingers at one
    configuration (thousands of rows within the radius) never holds all its pairs at once.
    """
    q = np.asarray(q, dtype=float)
    if radius_rad <= 0:
        _, ids = np.unique(np.round(q, 6), axis=0, return_inverse=True)
        return np.asarray(ids).ravel()
    n = len(q)
    tree = cKDTree(q)
    label = np.arange(n)  # a row of each group stands for it; merged block by block
    for block in chunks(n, GROUP_BLOCK_ROWS):
        rows = tree.indices[block]  # in the tree's order: each block is a compact region
        pairs = cKDTree(q[rows]).sparse_distance_matrix(tree, radius_rad, p=np.inf, output_type="ndarray")
        a, b = label[rows[pairs["i"]]], label[pairs["j"]]
        linked = a != b
        if linked.any():
            graph = coo_matrix((np.ones(int(linked.sum())), (a[linked], b[linked])), shape=(n, n))
            label = connected_components(graph, directed=False)[1][label]
    _, first, inverse = np.unique(label, return_index=True, return_inverse=True)
    return np.argsort(np.argsort(first))[inverse.ravel()]


GROUP_BLOCK_ROWS = 2048


PATH_BLOCKS_PER_FOLD = 10  # path data: blocks of neighbouring configurations per fold
EXTREME_RANKS = 2  # each joint's lowest and highest configurations dealt by rule (``range_keeping_deal``)
SUBFOLDS = 2  # each fold's groups dealt into this many sub-folds: the inner folds of a nested selection


class FoldIds(np.ndarray):
    """Fold of each row (an int array), with the rows each fold's training leaves out beside its
    own: ``exclude[k]`` (row indices, k indexing the sorted fold ids) or None when there are none.
    Indexing or arithmetic gives plain fold ids without exclusions."""

    exclude: tuple[np.ndarray, ...] | None = None
    sub: np.ndarray | None = None  # sub-fold of each row (whole groups), None for path data

    def __array_finalize__(self, obj):
        self.exclude = None
        self.sub = None


def canonical(q: np.ndarray, group: np.ndarray) -> np.ndarray:
    """Each group's rank among the groups in the lexicographic order of its smallest configuration:
    a numbering of the groups that the order of the rows does not change (``groups`` numbers them in
    order of each group's first row)."""
    config = groups(q)  # distinct configurations, numbered in lexicographic order
    first = np.full(int(group.max()) + 1, len(q))
    np.minimum.at(first, group, config)
    return np.argsort(np.argsort(first))


def fold_ids(q: np.ndarray, folds: int, seed: int = 0, radius_rad: float = 0.0) -> FoldIds:
    """Fold of each row, whole neighbour groups at a time, folds of nearly equal group count.

    The design depends on the configurations alone, never on the order of the rows: the same rows
    in any order get the same fold each (groups numbered by their content, ``canonical``; the seed
    draws among them). Each joint's extreme configurations are dealt first, to folds whose training
    keeps the joint's range (``range_keeping_deal``); the rest at random.

    When the neighbour groups chain most of the data together (the largest holds more than
    1/folds of the rows: a path logged along a program, every row a neighbour of the next), blocks
    of neighbouring configurations take the place of groups and each fold's training leaves out the
    rows within radius_rad of it (``path_fold_ids``)."""
    q = np.asarray(q, dtype=float)
    group = groups(q, radius_rad)
    n_groups = int(group.max()) + 1
    if radius_rad > 0 and np.bincount(group).max() * folds > len(q):
        distinct = int(groups(q).max()) + 1
        if distinct < folds:
            raise ValueError(f"only {distinct} distinct configurations: too few for {folds}-fold cross-validation")
        return path_fold_ids(q, folds, seed, radius_rad)
    if n_groups < folds:
        raise ValueError(f"only {n_groups} distinct configurations: too few for {folds}-fold cross-validation")
    group = canonical(q, group)[group]
    rng = np.random.default_rng(seed)
    fold_of_group, order = range_keeping_deal(q, group, n_groups, folds, rng)
    sub_of_group = np.empty(n_groups, dtype=int)  # within each fold, its groups in the drawn order in turn
    for k in range(folds):
        mine = order[fold_of_group[order] == k]
        sub_of_group[mine] = np.arange(len(mine)) % SUBFOLDS
    out = fold_of_group[group].view(FoldIds)
    out.sub = sub_of_group[group]
    return out


def range_keeping_deal(q: np.ndarray, group: np.ndarray, n_groups: int, folds: int,
                       rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(fold of each group, the groups in the drawn order): every fold's training keeps as much of
    every joint's range as the data allow.

    A fold that holds out a joint's extreme configurations leaves its training a narrower range of
    that joint, and a term of that joint is then estimated on the rest and scored where the training
    never reached (an IRB4600 measured joint by joint, 6 angles a joint: the fold that held out both
    ends of the elbow's sweep gained nothing from the elbow's compliance, the folds holding its inner
    angles 40%; which fold drew the ends decided whether an effect was found at all). So the groups
    that hold a joint's EXTREME_RANKS lowest or highest values are dealt first, lowest rank first, each
    to the fold (of those below their share) whose training then loses the least of every joint's range
    (summed as fractions of each range); the draw settles ties. The other groups follow in the drawn
    order, each to a fold with the fewest groups.

    Two ranks are what the guarantee needs: with a joint's two lowest configurations in two folds,
    every training keeps one of them, so no fold loses more of the range than the step from the lowest
    to the next. Dealing more ranks by rule takes the draw out of ever more of the design (on a 19-joint
    tree, 2 x 5 ranks a side would place up to 190 of 1000 groups), and the folds then stop being the
    random sample of the data the held-out scores stand for: the Agile Justin data's held-out mean moved
    from 3.09 to 3.13 mm with 5 ranks, back to 3.09 with 2."""
    order = rng.permutation(n_groups)
    position = np.empty(n_groups, dtype=int)
    position[order] = np.arange(n_groups)
    fold_rank = rng.permutation(folds)  # ties between folds: in a drawn order
    n_joints = q.shape[1]
    lo = np.full((n_groups, n_joints), np.inf)
    hi = np.full((n_groups, n_joints), -np.inf)
    np.minimum.at(lo, group, q)
    np.maximum.at(hi, group, q)
    lowest, highest = lo.min(0), hi.max(0)
    span = highest - lowest
    moving = span > 0
    joints = np.arange(n_joints)
    # each joint's groups from its lowest (highest) value, ties in the drawn order
    low = np.stack([np.lexsort((position, lo[:, j])) for j in range(n_joints)])
    high = np.stack([np.lexsort((position, -hi[:, j])) for j in range(n_joints)])
    ranks = min(EXTREME_RANKS, n_groups)
    extremes = []
    for r in range(ranks):
        for j in np.flatnonzero(moving):
            extremes.extend((low[j, r], high[j, r]))
    extremes = list(dict.fromkeys(int(g) for g in extremes))  # first time each group is met
    depth = min(n_groups, len(extremes) + 1)  # a training's extreme lies within the first `depth` of each list
    low, high = low[:, :depth], high[:, :depth]
    fold_of_group = np.full(n_groups, -1)
    count = np.zeros(folds, dtype=int)
    share = -(-n_groups // folds)

    def lost(k: int) -> float:
        """Fraction of each moving joint's range fold k's training would lose, summed."""
        first_low = np.argmax(fold_of_group[low] != k, axis=1)
        first_high = np.argmax(fold_of_group[high] != k, axis=1)
        train_lo = lo[low[joints, first_low], joints]
        train_hi = hi[high[joints, first_high], joints]
        return float(np.sum(((train_lo - lowest) + (highest - train_hi))[moving] / span[moving]))

    for g in extremes:
        best = None
        for k in sorted(range(folds), key=lambda k: fold_rank[k]):
            if count[k] >= share:
                continue
            fold_of_group[g] = k
            key = (round(lost(k), 12), count[k])
            if best is None or key < best[0]:
                best = (key, k)
        fold_of_group[g] = best[1]
        count[best[1]] += 1
    for g in order:
        if fold_of_group[g] < 0:
            k = min(range(folds), key=lambda k: (count[k], fold_rank[k]))
            fold_of_group[g] = k
            count[k] += 1
    return fold_of_group, order


def path_fold_ids(q: np.ndarray, folds: int, seed: int, radius_rad: float) -> FoldIds:
    """Folds for path data: PATH_BLOCKS_PER_FOLD blocks of neighbouring configurations per fold (fewer
    when rows are few), whole blocks to a fold at random; each fold's training excludes the rows of
    other folds within radius_rad (max over joints) of any of its rows.

    The blocks come from the configurations, not from the order of the rows: centres picked by
    farthest-point sampling (from the lexicographically first configuration, each next the one
    farthest from those picked, max over joints), each distinct configuration in the block of its
    nearest centre. Along a path these are stretches of it (and the pieces of other stretches that
    cross the same place): the same blocks whatever order the rows come in, and identical
    configurations always in one block."""
    n = len(q)
    n_blocks = max(folds, min(folds * PATH_BLOCKS_PER_FOLD, n // 2))
    config = groups(q)
    distinct = np.unique(np.round(q, 6), axis=0)
    n_blocks = min(n_blocks, len(distinct))
    centres = np.empty(n_blocks, dtype=int)
    centres[0] = 0
    far = np.abs(distinct - distinct[0]).max(axis=1)
    for b in range(1, n_blocks):
        centres[b] = int(np.argmax(far))
        far = np.minimum(far, np.abs(distinct - distinct[centres[b]]).max(axis=1))
    _, block_of_config = cKDTree(distinct[centres]).query(distinct, p=np.inf)
    block = np.asarray(block_of_config)[config]
    order = np.random.default_rng(seed).permutation(n_blocks)
    fold_of_block = np.empty(n_blocks, dtype=int)
    fold_of_block[order] = np.arange(n_blocks) % folds
    out = fold_of_block[block].view(FoldIds)
    exclude = []
    for k in range(folds):
        own = out == k
        others = np.flatnonzero(~own)
        dist, _ = cKDTree(q[own]).query(q[others], p=np.inf, distance_upper_bound=radius_rad)
        exclude.append(others[dist <= radius_rad])
        if 2 * len(exclude[-1]) > len(others):
            raise ValueError(
                f"the {n} configurations keep returning to the same places (more than half of the rows lie within "
                f"{np.rad2deg(radius_rad):.0f} deg of a block held out for {folds}-fold cross-validation): too few "
                f"configurations a fit has not seen to score it on; measure more distinct poses")
    out.exclude = tuple(exclude)
    return out


class FoldFactors:
    """The Jacobian J (3 rows per measurement, p columns) and residuals r of a linearised model,
    kept as one R factor of [J | r] per fold, a block of rows at a time.

    Everything the held-out steps need is in these (p + 1) x (p + 1) factors: the normal
    equations of any fold's training rows over any subset of columns, and the R factor of
    all rows (``r_all``) for the identifiability analysis.
    """

    def __init__(self, folds: np.ndarray, p: int):
        exclude = getattr(folds, "exclude", None)  # FoldIds: rows each fold's training also leaves out
        self.folds = np.asarray(folds)
        self.ids, self.index = np.unique(self.folds, return_inverse=True)
        self.index = self.index.ravel()
        self.p = p
        self._acc = [RFactor(p + 1) for _ in self.ids]
        self._gap = None  # (folds, N) bool: rows left out of each fold's training beside its own
        if exclude is not None and any(len(e) for e in exclude):
            self._gap = np.zeros((len(self.ids), len(self.folds)), dtype=bool)
            for k, rows in enumerate(exclude):
                self._gap[k, rows] = True
            self._gap_acc = [RFactor(p + 1) for _ in self.ids]
            # the inner folds of a nested selection leave out the gaps of two folds at once: the rows
            # of each (fold, which folds' training leaves them out) class kept apart (``inner``)
            bits = (self._gap * (1 << np.arange(len(self.ids)))[:, None]).sum(0)
            keys = self.index * (1 << len(self.ids)) + bits
            self._classes = np.unique(keys[bits > 0])
            self._class_of = np.full(len(self.folds), -1)
            self._class_of[bits > 0] = np.searchsorted(self._classes, keys[bits > 0])
            self._class_acc = [RFactor(p + 1) for _ in self._classes]
        sub = getattr(folds, "sub", None)  # FoldIds: sub-folds, the inner folds of a nested selection
        self._sub = None if sub is None or self._gap is not None else np.asarray(sub)
        if self._sub is not None:
            self._n_sub = int(self._sub.max()) + 1
            self._sub_grams = np.zeros((len(self.ids), self._n_sub, p + 1, p + 1))
        self._grams = None
        self._all_grams = None
        self._r_all = None

    def add(self, rows, j: np.ndarray, r: np.ndarray) -> None:
        """Rows (a slice or indices of the measurements): j (n, 3, p), r (n, 3)."""
        n = len(r)
        block = np.concatenate([np.reshape(j, (3 * n, self.p)), np.reshape(r, (3 * n, 1))], axis=1)
        fold = np.repeat(self.index[rows], 3)
        for k, acc in enumerate(self._acc):
            acc.add(block[fold == k])
        if self._gap is not None:
            for k, acc in enumerate(self._gap_acc):
                acc.add(block[np.repeat(self._gap[k, rows], 3)])
            cls = np.repeat(self._class_of[rows], 3)
            for c in np.unique(cls[cls >= 0]):
                self._class_acc[c].add(block[cls == c])
        if self._sub is not None:
            sub = np.repeat(self._sub[rows], 3)
            for k in np.unique(fold):
                for s in range(self._n_sub):
                    mine = block[(fold == k) & (sub == s)]
                    self._sub_grams[k, s] += mine.T @ mine
        self._grams = None
        self._all_grams = None
        self._r_all = None

    @property
    def factors(self) -> list[np.ndarray]:
        return [acc.r for acc in self._acc]

    def r_all(self) -> np.ndarray:
        """R factor of [J | r] over every row (made once after the last ``add``)."""
        if self._r_all is None:
            self._r_all = stacked_r(self.factors)
        return self._r_all

    def training(self, k: int):
        """Normal matrix J^T J and J^T r of every row outside fold k (k indexes self.ids) and outside
        its gap (the rows of other folds too close to it, path data)."""
        if self._grams is None:  # every fold's training Gram matrix, once: the total less the fold's own
            grams, total, _ = self._fold_grams()
            self._grams = [total - g for g in grams]
            if self._gap is not None:
                self._grams = [g - a.r.T @ a.r for g, a in zip(self._grams, self._gap_acc)]
        g = self._grams[k]
        return g[: self.p, : self.p], g[: self.p, self.p]

    def _fold_grams(self):
        """([J | r]^T [J | r] of each fold's rows], of every row, [of each gap class's rows])."""
        if self._all_grams is None:
            grams = [f.T @ f for f in self.factors]
            classes = [a.r.T @ a.r for a in self._class_acc] if self._gap is not None else []
            self._all_grams = (grams, np.sum(grams, axis=0), classes)
        return self._all_grams

    def outer(self) -> list:
        """(training Gram, held-out Gram) of [J | r] for each fold: the cross-validation over every row,
        in the form ``inner`` gives."""
        grams, _, _ = self._fold_grams()
        out = []
        for k in range(len(self.ids)):
            self.training(k)
            out.append((self._grams[k], grams[k]))
        return out

    def inner_parts(self, k: int):
        """(Gram of fold k's training rows, the sub-fold Grams (folds, sub-folds, p+1, p+1), the (fold,
        sub-fold) pairs held out in turn): each inner training of ``inner`` is the first less one of the
        second, without a copy of either; None for path data, whose inner trainings also leave
        out gaps (use ``inner``)."""
        if self._sub is None:
            return None
        grams, total, _ = self._fold_grams()
        pairs = [(j, s) for j in range(len(self.ids)) if j != k for s in range(self._n_sub)
                 if self._sub_grams[j, s].any()]
        return total - grams[k], self._sub_grams, np.array(pairs, dtype=int).reshape(-1, 2)

    def inner(self, k: int) -> list:
        """(training Gram, held-out Gram) of [J | r] for each inner fold of fold k's training rows (k
        indexes self.ids): the sub-folds of the other folds (``FoldIds.sub``: whole neighbour groups),
        or for path data the other folds, each held out in turn from fold k's training rows.
        There an inner training leaves out the gaps of both folds, an inner held-out fold the rows of
        fold k's gap: nothing of fold k, or too close to it, enters a choice made for fold k."""
        grams, total, classes = self._fold_grams()
        n = len(self.ids)
        out = []
        if self._sub is not None:
            for j in range(n):
                for held in (self._sub_grams[j] if j != k else ()):
                    if held.any():  # an empty sub-fold holds nothing out
                        out.append((total - grams[k] - held, held))
            return out
        for j in range(n):
            if j == k:
                continue
            train, held = total - grams[k] - grams[j], grams[j].copy()
            if self._gap is not None:
                for key, g in zip(self._classes, classes):
                    fold, bits = int(key) >> n, int(key) & ((1 << n) - 1)
                    if fold not in (k, j) and (bits >> k & 1 or bits >> j & 1):
                        train = train - g
                    if fold == j and bits >> k & 1:
                        held = held - g
            out.append((train, held))
        return out

    def inner_sse(self, k: int) -> float:
        """Held-out sum of squares of the inner folds of fold k's training rows (``inner``), every column
        estimated on each inner training: how a model does on fold k's training rows alone, for a choice
        between models made for fold k."""
        out = 0.0
        for train, held in self.inner(k):
            w = np.append(-_solve(train[: self.p, : self.p], train[: self.p, self.p]), 1.0)
            out += float(w @ held @ w)
        return out

    def steps(self, cols, penalty=None, deviation=None, lams=(0.0,)) -> np.ndarray:
        """Gauss-Newton steps over the columns cols on each fold's training rows, (len(lams), folds, p),
        zero outside cols. Optional L2 prior lam * sum(penalty * (deviation + step)^2) over cols."""
        cols = np.asarray(cols, dtype=int)
        penalty = np.zeros(len(cols)) if penalty is None else penalty
        deviation = np.zeros(len(cols)) if deviation is None else deviation
        out = np.zeros((len(lams), len(self.ids), self.p))
        for k in range(len(self.ids)):
            normal, grad = self.training(k)
            normal, grad = normal[np.ix_(cols, cols)], grad[cols]
            for g, lam in enumerate(lams):
                out[g, k, cols] = -_solve(normal + lam * np.diag(penalty), grad + lam * penalty * deviation)
        return out


class PointFoldFactors(FoldFactors):
    """``FoldFactors`` of a linearised model whose rows also measure an unknown point each (point-form
    data: a seating's point, estimated with the model in every training), the points eliminated.

    Besides the model's p columns, each row has a derivative over its own point's position
    (``add``'s pj, (n, 3, 3)): a point's three columns touch only its own rows. Every training's
    normal equations over [J | r] are given with its points eliminated, the Schur complement
    G - S^T N^+ S (G the training rows' Gram of [J | r], S = P^T [J | r] and N = P^T P per point);
    each held-out Gram is that of the held-out rows with their points at the training's estimate,
    which moves with the model's step w = [step; 1] as -N^+ S w. So every sum of squares, step and
    held-out error over the model's columns is the one the point columns would give as columns of
    their own, from (p + 1) x (p + 1) matrices. A point without training rows stays where it is.

    Kept per atom (the rows of one fold and one sub-fold, or of one fold and one set of trainings that
    leave them out as a gap): the Gram of [J | r], and per (atom, point) present S and N. The R factor
    of all rows (``r_all``) is of the rows with their points projected out, [J | r] - P N^+ S over all
    rows, which takes a second pass over the rows (``add_projected``).
    """

    def __init__(self, folds: np.ndarray, p: int, point: np.ndarray, n_points: int):
        exclude = getattr(folds, "exclude", None)
        sub = getattr(folds, "sub", None)
        self.folds = np.asarray(folds)
        self.ids, self.index = np.unique(self.folds, return_inverse=True)
        self.index = self.index.ravel()
        self.p = p
        n = len(self.folds)
        bits = np.zeros(n, dtype=np.int64)
        if exclude is not None:
            for k, rows in enumerate(exclude):
                bits[rows] |= 1 << k
        self._path = exclude is not None and bool(bits.any())
        self._sub = None if sub is None or self._path else np.asarray(sub)
        second = bits if self._path else (self._sub if self._sub is not None else np.zeros(n, dtype=np.int64))
        atoms, self._atom = np.unique(np.stack([self.index, second], axis=1), axis=0, return_inverse=True)
        self._atom = self._atom.ravel()
        self._atom_fold, self._atom_second = atoms[:, 0], atoms[:, 1]
        self.point, self.n_points = np.asarray(point), n_points
        pairs, self._pair = np.unique(self._atom * n_points + self.point, return_inverse=True)
        self._pair = self._pair.ravel()
        self._pair_atom, self._pair_point = pairs // n_points, pairs % n_points
        self._gram = np.zeros((len(atoms), p + 1, p + 1))
        self._cross = np.zeros((len(pairs), 3, p + 1))  # P^T [J | r] per (atom, point)
        self._pp = np.zeros((len(pairs), 3, 3))  # P^T P per (atom, point)
        self._all = RFactor(p + 1)
        self._cache: dict = {}

    def add(self, rows, j: np.ndarray, r: np.ndarray, pj: np.ndarray) -> None:
        """Rows (a slice or indices of the measurements): j (n, 3, p), r (n, 3), pj (n, 3, 3) d r / d point."""
        rows = np.arange(len(self.folds))[rows]
        block = np.concatenate([j, r[:, :, None]], axis=2)  # (n, 3, p + 1)
        flat = block.reshape(-1, self.p + 1)
        atom = np.repeat(self._atom[rows], 3)
        for a in np.unique(atom):
            mine = flat[atom == a]
            self._gram[a] += mine.T @ mine
        pair = self._pair[rows]
        np.add.at(self._cross, pair, np.einsum("nci,nca->nia", pj, block))
        np.add.at(self._pp, pair, np.einsum("nci,ncj->nij", pj, pj))
        self._cache.clear()

    def _sums(self, atoms: np.ndarray):
        """(Gram of [J | r], S (points, 3, p + 1), N (points, 3, 3)) over the atoms marked."""
        sel = atoms[self._pair_atom]
        s = np.zeros((self.n_points, 3, self.p + 1))
        n = np.zeros((self.n_points, 3, 3))
        np.add.at(s, self._pair_point[sel], self._cross[sel])
        np.add.at(n, self._pair_point[sel], self._pp[sel])
        return self._gram[atoms].sum(axis=0), s, n

    def _moves(self, train: np.ndarray):
        """(the training's Gram of [J | r], points eliminated; M (points, 3, p + 1): each point's estimate
        moves by M w with the model's step w = [step; 1])."""
        key = ("train", train.tobytes())
        if key not in self._cache:
            g, s, n = self._sums(train)
            m = -np.linalg.pinv(n, hermitian=True) @ s
            self._cache[key] = (g + _inner(s, m), m)
        return self._cache[key]

    def _pair_of(self, train: np.ndarray, held: np.ndarray):
        """(training Gram, held-out Gram) of [J | r], the points eliminated as the class docstring says."""
        t, m = self._moves(train)
        g, s, n = self._sums(held)
        cross = _inner(s, m)
        return t, g + cross + cross.T + _inner(m, n @ m)

    def _train_mask(self, k: int, also: int | None = None) -> np.ndarray:
        """Atoms of fold k's training (k indexes self.ids), less fold `also` (and both folds' gaps)."""
        out = self._atom_fold != k
        if also is not None:
            out &= self._atom_fold != also
        if self._path:
            out &= (self._atom_second >> k & 1) == 0
            if also is not None:
                out &= (self._atom_second >> also & 1) == 0
        return out

    @property
    def factors(self) -> list[np.ndarray]:
        """One R factor of [J | r] over every row, the points projected out (the normal equations of all
        rows with every point estimated)."""
        return [self.r_all()]

    def add_projected(self, rows, j: np.ndarray, r: np.ndarray, pj: np.ndarray) -> None:
        """The second pass, after every row was given to ``add``: the same rows, for ``r_all``."""
        if "all" not in self._cache:
            self._cache["all"] = self._moves(np.ones(len(self._gram), bool))[1]
        m = self._cache["all"]
        block = np.concatenate([j, r[:, :, None]], axis=2)
        block = block + pj @ m[self.point[rows]]
        self._all.add(block.reshape(-1, self.p + 1))

    def r_all(self) -> np.ndarray:
        return self._all.r

    def column_norms(self) -> np.ndarray:
        """Norms of the columns of [J | r] over every row, points not eliminated."""
        return np.sqrt(np.clip(np.diagonal(self._gram.sum(axis=0)), 0.0, None))

    def training(self, k: int):
        g, _ = self._moves(self._train_mask(k))
        return g[: self.p, : self.p], g[: self.p, self.p]

    def outer(self) -> list:
        return [self._pair_of(self._train_mask(k), self._atom_fold == k) for k in range(len(self.ids))]

    def inner_parts(self, k: int):
        return None  # the inner trainings' points are eliminated each on its own: no shared Gram to subtract

    def inner(self, k: int) -> list:
        out = []
        for j in range(len(self.ids)):
            if j == k:
                continue
            if self._sub is not None:  # each sub-fold of fold j held out from fold k's training
                for s in np.unique(self._atom_second[self._atom_fold == j]):
                    held = (self._atom_fold == j) & (self._atom_second == s)
                    out.append(self._pair_of(self._train_mask(k) & ~held, held))
            else:
                held = self._atom_fold == j
                if self._path:
                    held &= (self._atom_second >> k & 1) == 0
                out.append(self._pair_of(self._train_mask(k, j), held))
        return out

    def point_steps(self, k: int, steps: np.ndarray) -> np.ndarray:
        """(len(steps), points, 3): each point's move in fold k's training with the model's steps (s, p)."""
        _, m = self._moves(self._train_mask(k))
        w = np.concatenate([steps, np.ones((len(steps), 1))], axis=1)
        return np.einsum("pia,sa->spi", m, w)

    def heldout_errors(self, columns, r: np.ndarray, steps: np.ndarray) -> np.ndarray:
        """``heldout_errors`` with the points: columns yields (rows slice, J rows (n, 3, p), pj (n, 3, 3))."""
        moves = [self.point_steps(k, steps[:, k, :]) for k in range(len(self.ids))]
        errs = np.empty((len(steps), len(r)))
        for rows, j, pj in columns:
            fold = self.index[rows]
            point = self.point[rows]
            out = errs[:, rows]
            for k in np.unique(fold):
                sel = np.flatnonzero(fold == k)
                moved = (j[sel].reshape(-1, self.p) @ steps[:, k, :].T).reshape(len(sel), 3, len(steps))
                moved += np.einsum("nij,snj->nis", pj[sel], moves[k][:, point[sel]])
                pred = r[rows][sel][:, :, None] + moved
                out[:, sel] = np.sqrt(np.sum(pred * pred, axis=1)).T
        return errs


def _inner(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """sum over points of a_p^T b_p for (points, 3, m) stacks: one matrix product."""
    return a.reshape(-1, a.shape[2]).T @ b.reshape(-1, b.shape[2])


# The prior weights a nested ridge chooses among (``ridge_steps``), each relative to a penalised column's own
# squared norm over the training rows: from none to a prior that weighs like 1% of the rows, a factor 100
# apart (finer grids changed Agile Justin's held-out mean by under 0.005 mm and cost twice the solves). A
# fit of hundreds of effect parameters (a tree's compliance at every place) leaves directions its training
# rows barely see (scaled normal matrix conditioned ~1e11 on Agile Justin, where the folds choose 1e-6);
# with no weight an unlucky fold's step along them can cost more than all the rest gains.
RIDGE_GRID = (0.0, 1e-8, 1e-6, 1e-4, 1e-2)


def ridge_steps(factors: FoldFactors, cols, penalised: np.ndarray, deviation: np.ndarray,
                grid=RIDGE_GRID) -> tuple[np.ndarray, np.ndarray]:
    """(steps (1, folds, p), each fold's chosen weight): each fold's Gauss-Newton step over cols with an L2
    prior pulling the penalised columns' values (the linearisation point's, ``deviation`` over cols, plus
    the step) towards zero, its weight lam * the column's squared norm over the training rows, lam from
    grid chosen inside the fold's own training rows (``FoldFactors.inner``: the held-out sum of squares
    of the inner folds, summed; the smallest weight on a tie). Nothing of a fold decides its own weight."""
    cols = np.asarray(cols, dtype=int)
    penalised, deviation = np.asarray(penalised, bool), np.asarray(deviation, dtype=float)
    idx = np.concatenate([cols, [factors.p]])
    out = np.zeros((1, len(factors.ids), factors.p))
    chosen = np.zeros(len(factors.ids))

    def step(normal, grad, lam):
        pen = lam * np.diag(normal) * penalised
        return -_solve(normal + np.diag(pen), grad + pen * deviation)

    for k in range(len(factors.ids)):
        sse = np.zeros(len(grid))
        for train, held in factors.inner(k):
            t, h = train[np.ix_(idx, idx)], held[np.ix_(idx, idx)]
            for g, lam in enumerate(grid):
                w = np.append(step(t[:-1, :-1], t[:-1, -1], lam), 1.0)
                sse[g] += w @ h @ w
        best = int(np.argmin(sse))
        normal, grad = factors.training(k)
        out[0, k, cols] = step(normal[np.ix_(cols, cols)], grad[cols], grid[best])
        chosen[k] = grid[best]
    return out, chosen


def training_rows(folds: np.ndarray, k: int) -> np.ndarray:
    """Rows of fold k's training (k indexes the sorted fold ids): every other fold, less its gap."""
    folds_arr = np.asarray(folds)
    train = folds_arr != np.unique(folds_arr)[k]
    exclude = getattr(folds, "exclude", None)
    if exclude is not None:
        train[exclude[k]] = False
    return np.flatnonzero(train)


def inner_fold_ids(folds: np.ndarray, k: int) -> tuple[np.ndarray, FoldIds]:
    """(fold k's training rows, their fold ids with the gaps among them): the folds of a choice made
    inside fold k's training (nested cross-validation), the other folds held out in turn."""
    rows = training_rows(folds, k)
    inner = np.asarray(folds)[rows].view(FoldIds)
    exclude = getattr(folds, "exclude", None)
    if exclude is not None:
        at = np.full(len(folds), -1)
        at[rows] = np.arange(len(rows))
        inner.exclude = tuple(at[e][at[e] >= 0] for i, e in enumerate(exclude) if i != k)
    return rows, inner


def heldout_errors(columns, r: np.ndarray, factors: FoldFactors, steps: np.ndarray) -> np.ndarray:
    """Held-out point errors (len(steps), N): |r_i + J_i step(fold of i)| for each set of steps.

    columns: iterable of (rows slice, J rows (n, 3, p)), the same columns the factors hold,
    over all rows in blocks; r (N, 3) residuals (predicted - measured) at the linearisation point.
    """
    errs = np.empty((len(steps), len(r)))
    for rows, j in columns:
        fold = factors.index[rows]
        out = errs[:, rows]  # a view: rows is a slice
        for k in np.unique(fold):
            sel = np.flatnonzero(fold == k)
            moved = (j[sel].reshape(-1, factors.p) @ steps[:, k, :].T).reshape(len(sel), 3, len(steps))
            pred = r[rows][sel][:, :, None] + moved
            out[:, sel] = np.sqrt(np.sum(pred * pred, axis=1)).T
    return errs


def one_step_heldout(j: np.ndarray, r: np.ndarray, folds: np.ndarray, penalty: np.ndarray | None = None,
                     deviation: np.ndarray | None = None, lams=(0.0,)) -> np.ndarray:
    """Held-out point errors (len(lams), N) of a linearised least-squares model.

    j: (N, 3, p) Jacobian and r: (N, 3) residuals (predicted - measured) at the
    all-rows fit; penalty (p,) and deviation (p,): an optional L2 prior
    lam * sum(penalty * (deviation + step)^2), evaluated for every lam.
    """
    p = j.shape[2]
    factors = FoldFactors(folds, p)
    blocks = [(rows, j[rows]) for rows in chunks(len(r))]
    for rows, jr in blocks:
        factors.add(rows, jr, r[rows])
    steps = factors.steps(np.arange(p), penalty, deviation, lams)
    return heldout_errors(blocks, r, factors, steps)


def _solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Normal equations: Cholesky when positive definite, least squares when (near) singular."""
    try:
        return cho_solve(cho_factor(a, lower=True, check_finite=False), b, check_finite=False)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(a, b, rcond=None)[0]
