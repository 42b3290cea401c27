"""Pose and distance characteristics after ISO 9283:1998 (manipulating industrial robots,
performance criteria and related test methods), position part.

Test poses (clause 6.8): a cube in the working space; P1 is its centre, P2 .. P5 lie on
the diagonals of the cube's diagonal plane (the rectangle through two opposite edges), at
10 % of the diagonal's length from its corners. The robot visits P1 .. P5 in that order,
n cycles (the standard asks for 30), and each attained position x_j is measured.

Pose accuracy (clause 7.2.1): the distance between the command position and the
barycentre of the attained positions,

    x_bar = (1/n) sum_j x_j  (likewise y, z)
    AP_P = sqrt((x_bar - x_c)^2 + (y_bar - y_c)^2 + (z_bar - z_c)^2)
    AP_x = x_bar - x_c,  AP_y = y_bar - y_c,  AP_z = z_bar - z_c

Pose repeatability (clause 7.2.2): the radius of the sphere about the barycentre,

    l_j = |x_j - x_bar|,  l_bar = (1/n) sum_j l_j,  S_l = sqrt(sum_j (l_j - l_bar)^2 / (n - 1))
    RP_l = l_bar + 3 S_l

Distance accuracy and repeatability (clause 7.4), between two poses visited in the same
cycles (here P2 and P4, the ends of one diagonal):

    D_j = |x_1j - x_2j|,  D_c = |x_c1 - x_c2|,  D_bar = (1/n) sum_j D_j
    AD_P = D_bar - D_c,   RD = 3 S_D,  S_D = sqrt(sum_j (D_j - D_bar)^2 / (n - 1))

Orientation characteristics (AP_a, AP_b, AP_c, RP_a ..) are not computed: position-only
instruments (laser trackers) give none. Units: mm.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

POSES = ("P1", "P2", "P3", "P4", "P5")
# The standard's table of the number of cycles asks for 30 for pose accuracy and repeatability.
STANDARD_CYCLES = 30
# With two cycles both attained positions lie equally far from their barycentre (the midpoint), so
# S_l is 0 by construction and RP_l says nothing: three is the least that measures a spread of l_j.
MIN_CYCLES = 3
DISTANCE_PAIR = ("P2", "P4")
CORNER_FRACTION = 0.10  # clause 6.8: P2 .. P5 at 10 % of the diagonal from the corners


def cube_points(centre_mm, side_mm: float, axes=None) -> np.ndarray:
    """P1 .. P5 (5, 3) of a cube with this centre and side; axes (3, 3): the cube's edge directions
    as columns (default the frame's own). The diagonal plane holds the edges along axis 1 at
    (-s/2, -s/2) and (+s/2, +s/2) of axes 0 and 2, so P2 and P4 are the ends of one diagonal."""
    axes = np.eye(3) if axes is None else np.asarray(axes, dtype=float)
    h = side_mm / 2.0
    corners = np.array([[-h, -h, -h], [h, -h, h], [h, h, h], [-h, h, -h]])  # around the diagonal rectangle
    scale = 1.0 - 2.0 * CORNER_FRACTION  # from the centre toward a corner, 10 % of the diagonal short of it
    local = np.vstack([np.zeros(3), scale * corners])
    return np.asarray(centre_mm, dtype=float) + local @ axes.T


@dataclass(frozen=True)
class PoseCharacteristics:
    pose: str
    n: int
    ap_mm: float  # AP_P
    ap_xyz_mm: tuple[float, float, float]  # AP_x, AP_y, AP_z
    rp_mm: float  # RP_l
    l_bar_mm: float
    s_l_mm: float
    barycentre_mm: tuple[float, float, float]


@dataclass(frozen=True)
class DistanceCharacteristics:
    poses: tuple[str, str]
    n: int
    commanded_mm: float  # D_c
    mean_mm: float  # D_bar
    ad_mm: float  # AD_P = D_bar - D_c
    rd_mm: float  # 3 S_D


def pose_characteristics(pose: str, commanded_mm, attained_mm) -> PoseCharacteristics:
    """AP and RP of one pose (clauses 7.2.1, 7.2.2); commanded (3,), attained (n, 3), n >= MIN_CYCLES."""
    x = np.asarray(attained_mm, dtype=float)
    if len(x) < MIN_CYCLES:
        raise ValueError(f"{pose}: {len(x)} attained positions; repeatability needs at least {MIN_CYCLES} cycles")
    bar = x.mean(axis=0)
    ap = bar - np.asarray(commanded_mm, dtype=float)
    l = np.linalg.norm(x - bar, axis=1)
    s_l = float(np.std(l, ddof=1))
    return PoseCharacteristics(pose, len(x), float(np.linalg.norm(ap)), tuple(map(float, ap)),
                               float(l.mean() + 3.0 * s_l), float(l.mean()), s_l, tuple(map(float, bar)))


def distance_characteristics(poses: tuple[str, str], commanded_mm, attained_a_mm, attained_b_mm
                             ) -> DistanceCharacteristics:
    """AD and RD between two poses (clause 7.4); attained positions paired by cycle, (n, 3) each."""
    a, b = np.asarray(attained_a_mm, dtype=float), np.asarray(attained_b_mm, dtype=float)
    if len(a) != len(b) or len(a) < 2:
        raise ValueError(f"{poses[0]}-{poses[1]}: needs the same cycles, at least 2, for both poses")
    d = np.linalg.norm(a - b, axis=1)
    d_c = float(np.linalg.norm(np.subtract(*commanded_mm)))
    return DistanceCharacteristics(poses, len(d), d_c, float(d.mean()), float(d.mean() - d_c),
                                   float(3.0 * np.std(d, ddof=1)))


def characteristics(pose: np.ndarray, cycle: np.ndarray, commanded_mm: np.ndarray, attained_mm: np.ndarray):
    """Every pose's AP and RP, and AD/RD between DISTANCE_PAIR where both were visited in two or
    more common cycles. pose (N,) labels, cycle (N,) ids, commanded and attained (N, 3).

    A pose's command position is the mean of its rows' commanded positions (one program point,
    the same in every cycle up to rounding); returns (list of PoseCharacteristics, DistanceCharacteristics or None).
    """
    pose, cycle = np.asarray(pose).astype(str), np.asarray(cycle)
    labels = [p for p in POSES if p in set(pose)] + sorted(set(pose) - set(POSES))
    out = [pose_characteristics(p, commanded_mm[pose == p].mean(axis=0), attained_mm[pose == p]) for p in labels]
    a, b = DISTANCE_PAIR
    common = sorted(set(cycle[pose == a]) & set(cycle[pose == b]))
    distance = None
    if len(common) >= 2:
        def rows(p):
            return np.array([np.flatnonzero((pose == p) & (cycle == c))[0] for c in common])
        ra, rb = rows(a), rows(b)
        distance = distance_characteristics(DISTANCE_PAIR, (commanded_mm[ra].mean(axis=0), commanded_mm[rb].mean(axis=0)),
                                            attained_mm[ra], attained_mm[rb])
    return out, distance
