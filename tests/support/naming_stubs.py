"""Made-up held-out scores for the naming rule alone (tests/unit/test_analyze.py and
tests/unit/test_discriminate.py): an explanation of a given held-out error, and a scorer
that answers the rule's tie questions with fixed values."""
from __future__ import annotations

import numpy as np

from cellcal.solvers.analysis.naming import Scored
from cellcal.solvers.analysis.effects import Term


def scored(cause: str, heldout_mean_mm: float, size: int = 1) -> Scored:
    term = Term(cause, {"joint": 2}, tuple(f"p{i}" for i in range(size)))
    return Scored(label=term.label(), cause=cause, where=term.where, heldout_errors=np.full(20, heldout_mean_mm),
                  theta=np.zeros(size), magnitude={}, x=np.zeros(0), terms=(term,))


class StubScorer:
    """Answers the naming rule's tie questions with fixed values (separation: residual sum of squares,
    mm^2, of one explanation refitted to the other's predictions)."""

    def __init__(self, pair_mean_mm: float = 1.0, nested: bool = False, separation_mm2: float = 1e6):
        self.pair_mean_mm, self.nested, self.separation = pair_mean_mm, nested, separation_mm2

    def separation_mm2(self, fitted, refitted):
        return self.separation

    def heldout_errors_mm(self, terms):
        return np.full(20, self.pair_mean_mm)

    def is_nested(self, inner, outer):
        return self.nested


BASELINE = scored("none", 1.0)
