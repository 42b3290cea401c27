"""One model-selection procedure for every cause that has places, nested inside the folds.

A cause with places (``Cause.search_places``: joint_compliance and backlash at each joint,
cyclic_joint_error at each (joint, order) and each joint's spline) is offered to the analysis
as the result of one forward search (``forward``): start from the combinable place with the
lowest held-out error, then add, one at a time, the place that lowers it most, and stop when the
best addition lowers it by less than GAIN. Richer places (a joint's spline: a whole periodic
function of one angle) join a second combination, grown the same way from the best place of all;
it is taken when it lowers the held-out rms by GAIN below the plain one (``forward``). Places that
share a ``slot`` (a joint's spline at its different knot counts and penalty weights) never combine.
The same search and the same stopping rule for every cause. Combinations across causes (a second
effect) are searched the same way, with the first effect in the model (``base``; where it was
itself chosen inside the folds, each fold's own choice: ``select``'s fold_bases).

GAIN is a parsimony rule, not the guard against false alarms (that is the nested score and the
naming rule's 10 % over geometry alone). An effect spread over many places, periodic errors of
one or two orders at each of six joints as collaborative arms show, adds a few percent a place:
at 10 % the search stopped after one to three places (a simulated UR10e of that kind, 200
poses: 0.32-0.37 mm held-out with geometry alone, 0.25-0.32 with the periodic error found, or
nothing named); at 7 % it finds all six joints (0.13-0.14 mm, 0.05-0.07 with the compliance the
search then adds as a second effect). At 5 % a wrist joint with no compliance joined the elbow's
in a sweep made to separate compliance from a periodic error.

Scores. The held-out sum of squares of geometry plus the places, one Gauss-Newton step per
fold (``LinearisedScorer``), computed from the scorer's per-fold Gram matrices of [J | r]
(``crossval.FoldFactors``): no pass over the rows. The columns every candidate of a step shares
(geometry, the places chosen so far, a first effect) are eliminated once per split, so a place
tried costs a solve of its own few columns.

Nesting. Every choice that looks at the data is made again inside each fold's training rows
alone: the search is run with inner folds (the other folds' sub-folds of whole neighbour groups,
each held out in turn from the training rows; for path data the other folds, gaps
respected: ``FoldFactors.inner``) among the places the fold's own training rows picked
(``extra["folds"]``: the orders of a periodic error, the joints whose spline is offered). Inside a fold the choice
may be none: the best single place must itself lower the error by GAIN. The held-out errors reported for the cause are each fold's own selection scored on that
fold (``nested_steps``): what the procedure, not the one model it picked from all rows, reaches
on poses it has not seen. The term offered, named and fitted in full is the search on all rows
(over the analysis' folds, among the places picked on all rows: ``extra["all"]``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.solvers.analysis.effects import Term
from cellcal.solvers.analysis.linearised_scorer import RIDGE, search_step, unit_scales

GAIN = 0.07  # a place joins (inside a fold: starts) a combination only if it lowers the held-out rms error 7%
BATCH_COLUMNS = 160  # the places of one step scored a batch at a time, their own columns together this many at most:
#                     each batch's held-out Gram grows with the square of its columns, each costs the common ones' once
#                     (a six-joint periodic case: 4.9 s CPU at 160, 6.1 at 384, 5.2 at 96; the same scores)


@dataclass(frozen=True)
class Selection:
    """A cause's forward search: on all rows, and inside each fold's training rows."""

    cause: str
    term: Term  # the places chosen on all rows, as one term (what is offered, named and fitted)
    parts: tuple[Term, ...]
    per_fold: tuple[tuple[Term, ...], ...]  # each fold's choice on its training rows alone (() for none)


class Scores:
    """Held-out sums of squares of geometry plus term sets, over the analysis' folds (fold None) or
    over the inner folds of one fold's training rows (fold k, indexing the sorted fold ids)."""

    def __init__(self, scorer):
        self.scorer = scorer
        factors = scorer.factors
        self.p = factors.p
        self.n_folds = len(factors.ids)
        self._factors = factors
        self._splits: dict = {}  # fold -> its splits' Grams (``_blocks``)
        self._cols: dict = {}

    def _split(self, fold):
        if fold not in self._splits:
            parts = None if fold is None else self._factors.inner_parts(fold)
            if parts is not None:
                self._splits[fold] = parts
            else:
                pairs = self._factors.outer() if fold is None else self._factors.inner(fold)
                self._splits[fold] = ([t for t, _ in pairs], [h for _, h in pairs])
        return self._splits[fold]

    def _blocks(self, fold, idx: np.ndarray):
        """(training, held-out) Grams of every split of `fold` at the columns idx, (splits, k, k) each."""
        split = self._split(fold)
        if len(split) == 3:  # every training: fold's training less a sub-fold
            train, sub, pairs = split
            h = sub[pairs[:, 0, None, None], pairs[:, 1, None, None], idx[None, :, None], idx[None, None, :]]
            return train[idx[:, None], idx][None] - h, h
        at = np.ix_(idx, idx)
        return np.array([t[at] for t in split[0]]), np.array([h[at] for h in split[1]])

    def cols(self, terms) -> np.ndarray:
        """The columns of geometry and terms these data estimate (``LinearisedScorer.estimated``)."""
        key = frozenset(map(id, terms))
        if key not in self._cols:
            self._cols[key] = self.scorer.estimated(tuple(terms))
        return self._cols[key]

    def _set_cols(self, terms) -> np.ndarray:
        """Each term's parameters as estimated beside the geometry alone (a combination whose terms the
        data cannot tell apart scores badly, and is not chosen)."""
        key = ("set", frozenset(map(id, terms)))
        if key not in self._cols:
            self._cols[key] = (np.unique(np.concatenate([self.cols((t,)) for t in terms])) if terms
                               else self.cols(()))
        return self._cols[key]

    def sum_squares(self, fold, common: tuple[Term, ...], extras) -> np.ndarray:
        """Held-out sum of squares, over the splits of `fold`, of geometry + common + each of extras (tuples
        of terms). The common columns are eliminated once (their Schur complement), so each extra costs a
        solve of its own few columns."""
        c = self._set_cols(common)
        own = [np.setdiff1d(self._set_cols(common + tuple(e)), c) for e in extras]
        batches = _batches(own, BATCH_COLUMNS)
        if len(batches) == 1:
            return self._sum_squares(fold, common, extras, c, own)
        out = np.empty(len(extras))
        for b in batches:
            out[b] = self._sum_squares(fold, common, [extras[i] for i in b], c, [own[i] for i in b])
        return out

    def _sum_squares(self, fold, common, extras, c, own) -> np.ndarray:
        """``sum_squares`` of extras whose own columns (beyond the common columns c) are own."""
        q = np.unique(np.concatenate(own)).astype(int) if own else np.zeros(0, int)
        nc, nq = len(c), len(q)
        idx = np.concatenate([c, q, [self.p]])
        train, held = self._blocks(fold, idx)
        # columns scaled to unit length and a vanishing ridge: a direction some training lacks entirely gets
        # no step instead of an arbitrary one (a fold short of what one place needs must not extrapolate);
        # the terms' own penalties (a spline's, ``base.part_penalty``) from each split's training, as scaled
        d2 = np.diagonal(train, axis1=1, axis2=2)[:, :-1]
        d, empty = unit_scales(d2)
        penalty = self.scorer.penalty
        common_penalty = penalty(common, c, d2[:, :nc])
        extra_penalties = [penalty(tuple(e), o, d2[:, nc + np.searchsorted(q, o)]) for e, o in zip(extras, own)]
        d = np.concatenate([d, np.ones((len(d), 1))], axis=1)
        train = train / d[:, :, None] / d[:, None, :]
        held = held / d[:, :, None] / d[:, None, :]
        gone = np.concatenate([empty, np.zeros((len(empty), 1), bool)], axis=1)
        train = np.where(gone[:, :, None] | gone[:, None, :], 0.0, train)
        eye = np.zeros(train.shape[1:])
        eye[np.arange(nc + nq), np.arange(nc + nq)] = 1.0
        train = train + (RIDGE + gone[:, :, None] * 1.0) * eye
        if common_penalty is not None:  # the common terms' penalties, before they are eliminated
            train[:, :nc, :nc] += common_penalty / d[:, :nc, None] / d[:, None, :nc]
        # common columns eliminated: x_C = w - X x_P for the extra columns' step x_P
        x = np.linalg.solve(train[:, :nc, :nc], train[:, :nc, nc:])  # (splits, nc, nq + 1)
        reduced = train[:, nc:, nc:] - train[:, nc:, :nc] @ x  # (splits, nq + 1, nq + 1)
        w = np.zeros((len(train), nc + nq + 1))
        w[:, :nc], w[:, -1] = -x[:, :, -1], 1.0  # common step alone, with the residual's 1
        hw = held @ w[:, :, None]
        base = np.einsum("si,si->s", w, hw[:, :, 0])
        # held-out Gram in the extra columns' coordinates: E = [-X; I; 0]
        he = held[:, :, nc:nc + nq] - held[:, :, :nc] @ x[:, :, :nq]  # H E, (splits, k, nq)
        g = he[:, nc:nc + nq, :] - np.swapaxes(x[:, :, :nq], 1, 2) @ he[:, :nc, :]  # E^T H E
        h = np.einsum("skq,sk->sq", he, w)  # E^T H w
        out = np.empty(len(extras))
        pos = [np.searchsorted(q, o) for o in own]
        by_size: dict[int, list[int]] = {}
        for i, o in enumerate(pos):
            by_size.setdefault(len(o), []).append(i)
        for m, which in by_size.items():
            if m == 0:
                out[which] = base.sum()
                continue
            at = np.array([pos[i] for i in which])  # (sets, m)
            a = reduced[:, at[:, :, None], at[:, None, :]]  # (splits, sets, m, m)
            penalised = [i for i in which if extra_penalties[i] is not None]
            if penalised:  # each extra's own penalties (its columns are not eliminated: added here)
                a = a.copy()
                for i in penalised:
                    scale = d[:, nc + pos[i]]
                    a[:, which.index(i)] += extra_penalties[i] / scale[:, :, None] / scale[:, None, :]
            step = -np.linalg.solve(a, reduced[:, at, nq][..., None])[..., 0]  # (splits, sets, m)
            quad = np.einsum("smi,smij,smj->sm", step, g[:, at[:, :, None], at[:, None, :]], step)
            out[which] = (base[:, None] + 2.0 * np.einsum("smi,smi->sm", step, h[:, at]) + quad).sum(axis=0)
        return np.where(out >= 0.0, out, np.inf)  # < 0: rounding of a step gone wild, never the best


def _batches(own, limit: int) -> list[list[int]]:
    """The extras (their own columns: own) in batches, in order, whose columns together stay within limit (an
    extra beyond it alone): each extra's score is the same in any batch, the Grams a batch needs stay small."""
    out, cols = [], set()
    for i, o in enumerate(own):
        more = cols | set(o.tolist())
        if out and len(more) > limit:
            out.append([i])
            cols = set(o.tolist())
        else:
            out[-1:] = [(out[-1] if out else []) + [i]]
            cols = more
    return out or [[]]


def offered(term: Term, fold) -> bool:
    """Is a place offered to the search on all rows (fold None) or inside fold k's training rows?"""
    if fold is None:
        return term.extra.get("all", True)
    return fold in term.extra.get("folds", (fold,))


def _same_slot(a: Term, b: Term) -> bool:
    """Are two places alternatives for one function (``extra["slot"]``: a joint's splines of different knot
    counts), of which a combination holds one at most?"""
    slot = a.extra.get("slot")
    return slot is not None and slot == b.extra.get("slot")


def forward(places, alone, scores: Scores, fold=None, base: tuple[Term, ...] = ()) -> tuple[Term, ...]:
    """The forward search (module docstring) among the places offered for `fold`; () when none is.

    `alone` are richer places (a joint's spline: a whole periodic function of one angle, many
    parameters where an order has two). Two combinations are grown, each from its best place: one
    of `places` alone and one of `places` and `alone` together (a spline at one joint, orders or
    splines at others); the richer one is chosen only when it lowers the held-out rms error by GAIN
    below the plain one, as any addition must. A few sinusoids are so named by their orders, while a
    real arm's per-joint errors (neither one sinusoid nor at one joint) take splines at several joints."""
    combinable = [t for t in places if offered(t, fold)]
    richer = [t for t in alone if offered(t, fold)]
    starts = combinable + richer
    if not starts:
        return ()
    sums = scores.sum_squares(fold, base, [()] + [(t,) for t in starts])
    if fold is not None and np.sqrt(sums[1:].min()) >= (1.0 - GAIN) * np.sqrt(sums[0]):
        return ()  # inside a fold the choice may be none: no place lowers the error by GAIN

    def grow(pool):
        at = [starts.index(t) for t in pool]
        i = at[int(np.argmin(sums[1 + np.array(at)]))]
        chosen, current = [starts[i]], sums[1 + i]
        adds = [t for t in pool if t is not chosen[0] and not _same_slot(t, chosen[0])]
        while adds:
            more = scores.sum_squares(fold, base + tuple(chosen), [(t,) for t in adds])
            best = int(np.argmin(more))
            if np.sqrt(more[best]) >= (1.0 - GAIN) * np.sqrt(current):
                break
            chosen.append(adds.pop(best))
            current = more[best]
            adds = [t for t in adds if not _same_slot(t, chosen[-1])]
        return tuple(chosen), current

    plain = grow(combinable) if combinable else None
    if not richer:
        return plain[0]
    rich = grow(starts)
    if plain is None or np.sqrt(rich[1]) < (1.0 - GAIN) * np.sqrt(plain[1]):
        return rich[0]
    return plain[0]


def select(cause, places, alone, scores: Scores, base: tuple[Term, ...] = (),
           fold_bases: tuple[tuple[Term, ...], ...] | None = None) -> Selection | None:
    """The cause's forward search on all rows and inside every fold; None when no place is offered.
    base: terms in the model throughout (a first effect); fold_bases: each fold's own base, when the base
    was itself chosen inside each fold (a first effect's ``Selection.per_fold``): a fold's search, and its
    score, then hold what that fold's training rows chose, never the all-rows choice."""
    parts = forward(places, alone, scores, None, base)
    if not parts:
        return None
    bases = fold_bases if fold_bases is not None else (base,) * scores.n_folds
    per_fold = tuple(forward(places, alone, scores, k, bases[k]) for k in range(scores.n_folds))
    obs, model = scores.scorer.obs, scores.scorer.model
    return Selection(cause.id, cause.combine(parts, len(obs), model.n_joints), parts, per_fold)


def nested_steps(scores: Scores, selection: Selection | None, bases: tuple[tuple[Term, ...], ...] = ()) -> np.ndarray:
    """(1, folds, p) each fold's step with its own selection (None: nothing) and its base (bases[k]; (): none),
    fitted on its training rows as the search scored it (``search_step``, with the terms' penalties)."""
    factors, scorer = scores.scorer.factors, scores.scorer
    out = np.zeros((1, scores.n_folds, scores.p))
    for k in range(scores.n_folds):
        terms = (bases[k] if bases else ()) + (selection.per_fold[k] if selection is not None else ())
        cols = scores._set_cols(terms)
        normal, grad = factors.training(k)
        normal = normal[np.ix_(cols, cols)]
        out[0, k, cols] = search_step(normal, grad[cols], scorer.penalty(terms, cols, np.diagonal(normal)))
    return out
