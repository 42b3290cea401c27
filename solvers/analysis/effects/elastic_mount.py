"""The whole robot on an elastic mount: it tilts and gives under its own gravity moment.

A mobile base on its suspension, a humanoid on its platform, a pedestal or a table: the
mount is one more elastic link, below the first joint. Under the gravity moment of
everything above it the robot tilts about the two horizontal axes through its base, and
the pivot (wherever it really is) adds a horizontal shift in proportion. No joint of the
model can take this up: the first joint is usually vertical, and a pitch joint higher up
only turns what is above it.

With unknown masses the moment about each horizontal axis is a combination of the
point-mass regressors of every link point (as for the joints, ``gravity``), so the model
stays linear in lumped coefficients: for each link point and each horizontal axis, the
targets turn about that axis through the base origin, and shift along each horizontal
direction, in proportion to the point's gravity moment about that axis. These are
Cartesian columns (the robot file has no parameter for the mount), in the instrument's
frame through the geometric fit's base transform.

The pivot's shift (``shifts``) is in the analysis' candidate of every branch together: its
columns are the same at every step of the full fit, which solves for them in closed form
(``extended_model``), so the shift costs little there (Agile Justin: 3.23 -> 3.13 mm held-out).
"""
from __future__ import annotations

import numpy as np

from cellcal.solvers.geometry import se3
from cellcal.solvers.geometry.gravity import point_mass_regressors
from cellcal.solvers.identification.measurement_model import predict

MIN_MOMENT_SPREAD = 1e-6  # a point whose moment never changes has no column (as for the joints)
PIVOT_SHIFT = True  # the candidate of every branch has the pivot's shift (a bench turns it off for its baseline)


def horizontal_axes(gravity) -> np.ndarray:
    """Two orthonormal axes (2, 3) normal to gravity in the base frame: base x (or y when x is
    vertical) made horizontal, then up x that."""
    g = np.asarray(gravity, dtype=float)
    up = -g / np.linalg.norm(g)
    first = np.eye(3)[0] if abs(up[0]) < 0.9 else np.eye(3)[1]
    first = first - (first @ up) * up
    first /= np.linalg.norm(first)
    return np.stack([first, np.cross(up, first)])


def mount_columns(model, layout, x, obs, points, shifts=False):
    """Cartesian columns (N, 3, m), their names, and the tilt of each axis as a place:
    {label: (N, m) with tilt = D @ theta (rad)}. points: (N, 3) link points in the base frame,
    mm, each once (every point of the tree weighs on the mount)."""
    n = len(obs)
    b = x[layout.base]
    rot = se3.rotvec_to_matrix(b[3:])
    p_base = (predict(layout, x, obs) - b[:3]) @ rot  # the targets in the base frame
    axes = horizontal_axes(model.gravity)
    turn_cols, shift_cols, regressors = [], [], []
    names = []
    for a, axis in enumerate(axes):
        axis_rows = np.broadcast_to(axis, (n, 3))
        moments = point_mass_regressors(axis_rows, np.zeros((n, 3)), points, model.gravity)
        keep = np.ptp(moments, axis=0) > MIN_MOMENT_SPREAD
        turn = np.cross(axis_rows, p_base) @ rot.T  # the targets turned about the axis, instrument frame
        for i in np.flatnonzero(keep):
            m = moments[:, i, None]
            turn_cols.append(turn * m)
            shift_cols.append([np.broadcast_to(rot @ h, (n, 3)) * m for h in axes] if shifts else [])
            regressors.append((a, moments[:, i]))
            names += [f"mount.tilt{a + 1}.m{i}"] + ([f"mount.tilt{a + 1}.m{i}.shift{h + 1}" for h in range(2)]
                                                     if shifts else [])
    if not names:
        return np.zeros((n, 3, 0)), [], {}
    cols = np.stack([c for t, s in zip(turn_cols, shift_cols) for c in (t, *s)], axis=2)
    places = {}
    per_point = 3 if shifts else 1
    for k, (a, moment) in enumerate(regressors):
        places.setdefault(f"mount.tilt{a + 1}", np.zeros((n, len(names))))[:, per_point * k] = moment
    return cols, names, places
