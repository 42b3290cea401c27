"""Physical sizes a person can believe: a joint's deflection (or stiffness) only where the data
determine it, a group's combined value where they do not.

An elastic model with many places that deflect (every joint rotation and bending axis of
a tree) can predict well while the split between places is arbitrary: two parallel torso
axes trade their deflections against each other, and a fit happily reports degrees on
one and minus degrees on the other. The fit's covariance says which places the data
separate. For each place p the deflection over the poses is linear in the term's
parameters, d_p = D_p theta (rad), so its estimate has a covariance D_p Cov D_p^T. We
report

- the place's deflection (std over the poses, its varying part: a constant is a
  geometric offset) and its standard error (rms over the poses), on its own when the
  deflection is at least DETERMINED_SIGMAS standard errors;
- otherwise the place joins the places whose deflection estimates it trades with
  (correlation of the pose-wise errors |r| > GROUP_R): the group's combined deflection,
  the members signed so that trading ones add, with its own standard error;
- a place that is neither determined nor traded with any other is reported as not
  determined: its estimate, its error and the bound the data put on it.

With masses in the robot file a serial joint's compliance c (rad/N m) is a parameter of
its own: the stiffness 1/c (N m/rad) is given with its standard error when c is
determined, and a lower bound on it when c is not significant. Without masses only
products of compliance and unknown mass moments are identified; a deflection is then the
physical size the data give, and no stiffness is claimed.

Standard errors assume independent residuals of equal spread (sigma from the fit's own
residuals): where an unmodelled effect dominates they are the right order, not exact.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import solve_triangular

from cellcal.solvers.estimation import identifiability, lsq

DETERMINED_SIGMAS = 3.0  # a size stands on its own at this many standard errors
GROUP_R = 0.5  # places whose deflection errors correlate this strongly are reported together


def theta_covariance_root(fit) -> np.ndarray:
    """L (n_theta, n_estimated) with Cov(theta) = L L^T; rows of unestimated theta are zero.

    From the R factor of the fit's Jacobian over its estimated unknowns (geometry
    included, so the deflections' uncertainty counts what the geometry can trade).
    """
    n_est = int(fit.estimated.sum())
    acc = lsq.RFactor(n_est)
    for _, j in fit.jacobian_chunks():
        acc.add(j.reshape(-1, n_est))
    r = acc.r
    n_rows = 3 * len(fit.residuals_mm)
    sigma = np.sqrt(np.sum(fit.residuals_mm**2) / max(n_rows - n_est, 1))
    diag = np.abs(np.diag(r))
    if diag.min() > 1e-12 * diag.max():
        r_inv = solve_triangular(r, np.eye(n_est))
    else:  # a direction the data do not see at all: its variance is unbounded, pinv keeps the rest
        r_inv = np.linalg.pinv(r)
    n_free = fit.model.n_free
    position = np.cumsum(fit.estimated) - 1  # index of each estimated unknown in r
    out = np.zeros((len(fit.theta), n_est))
    theta_est = fit.estimated[n_free:]
    out[theta_est] = sigma * r_inv[position[n_free:][theta_est]]
    return out


def place_sizes(places, theta: np.ndarray, cov_root: np.ndarray, compliance_index=None) -> tuple[list, dict]:
    """Sizes of a term's places. places: [(label, D (N, m))], deflection = D @ theta (rad);
    cov_root (m, k): Cov(theta) = cov_root cov_root^T. compliance_index: label -> the
    index of a theta entry that is that place's compliance in rad/N m (known masses).

    Returns (entries, flat): entries, one dict per place or group (JSON); flat, the
    numbers of the determined entries keyed by name, for the one-line-per-number report.
    """
    compliance_index = compliance_index or {}
    n = len(theta) and places[0][1].shape[0]
    labels, value, err_rows = [], [], []
    for label, d in places:
        d = d - d.mean(axis=0)  # the varying part
        cols = np.flatnonzero(np.any(d != 0, axis=0))
        labels.append(label)
        value.append(d[:, cols] @ theta[cols])
        err_rows.append((d[:, cols], cols))
    p = len(labels)
    cov = np.zeros((p, p))  # pose-averaged covariance of the places' deflection estimates, rad^2
    roots = [dc @ cov_root[cols] for dc, cols in err_rows]  # (N, k) each
    for a in range(p):
        for b in range(a, p):
            cov[a, b] = cov[b, a] = float(np.sum(roots[a] * roots[b])) / max(n, 1)
    std = np.array([np.sqrt(np.mean(v**2)) for v in value])
    err = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    determined = std >= DETERMINED_SIGMAS * err
    entries = []
    for a in np.flatnonzero(determined):
        entries.append(_entry([labels[a]], std[a], err[a], "determined"))
    grouped = np.zeros(p, bool)
    for members, sign in _merge(cov, np.flatnonzero(~determined), value):
        grouped[members] = True
        combined = sum(s * value[m] for s, m in zip(sign, members))
        combined_err = np.sqrt(max(float(sign @ cov[np.ix_(members, members)] @ sign), 0.0))
        combined_std = float(np.sqrt(np.mean(combined**2)))
        kind = "group" if combined_std >= DETERMINED_SIGMAS * combined_err else "group, not determined"
        entries.append(_entry([("-" if s < 0 else "") + labels[m] for s, m in zip(sign, members)],
                              combined_std, combined_err, kind,
                              max_abs_r=_max_offdiag(identifiability.correlation(cov), members)))
    for a in np.flatnonzero(~determined & ~grouped):
        entries.append(_entry([labels[a]], std[a], err[a], "not determined"))
    for e in entries:
        if len(e["places"]) == 1 and e["places"][0] in compliance_index:
            i = compliance_index[e["places"][0]]
            e.update(_stiffness(theta[i], float(np.linalg.norm(cov_root[i]))))
    return entries, _flat(entries)


def _entry(names, std_rad, err_rad, kind, **extra) -> dict:
    out = {"places": list(names), "kind": kind, "deflection_std_deg": float(np.rad2deg(std_rad)),
           "standard_error_deg": float(np.rad2deg(err_rad))}
    if kind == "not determined":
        out["below_deg"] = float(np.rad2deg(std_rad + DETERMINED_SIGMAS * err_rad))
    return {**out, **extra}


def _stiffness(c: float, c_err: float) -> dict:
    """Stiffness from a compliance in rad/N m: value and error when c is determined (and
    positive, as a spring is), else the lower bound the data put on it."""
    out = {"compliance_rad_per_Nm": float(c), "compliance_standard_error_rad_per_Nm": c_err}
    if c > 0 and c >= DETERMINED_SIGMAS * c_err:
        out.update(stiffness_Nm_per_rad=1.0 / c, stiffness_standard_error_Nm_per_rad=c_err / c**2)
    elif c_err > 0:  # (a compliance the fit held at 0 has no error and says nothing)
        out["stiffness_above_Nm_per_rad"] = 1.0 / (abs(c) + DETERMINED_SIGMAS * c_err)
    return out


def _merge(cov: np.ndarray, open_, value) -> list:
    """Groups of places not determined alone: agglomerative, the two groups whose combined
    deflection errors correlate most (|r| >= GROUP_R) merge first, signed so that places
    that trade against each other add; a group stops growing once its combined deflection
    is determined. Returns [(member indices, signs)] of groups with two members or more."""
    clusters = [(np.array([a]), np.ones(1)) for a in open_]
    done = []

    def spread(c):  # the combined estimate as a vector over all places: its covariance and size
        w = np.zeros(len(cov))
        w[c[0]] = c[1]
        return w

    while len(clusters) > 1:
        w = np.array([spread(c) for c in clusters])
        c_cov = w @ cov @ w.T
        corr = identifiability.correlation(c_cov)
        np.fill_diagonal(corr, 0.0)
        a, b = np.unravel_index(np.argmax(np.abs(corr)), corr.shape)
        if abs(corr[a, b]) < GROUP_R:
            break
        sign = -np.sign(corr[a, b])  # errors that rise together are traded: b enters with the opposite sign
        merged = (np.r_[clusters[a][0], clusters[b][0]], np.r_[clusters[a][1], sign * clusters[b][1]])
        clusters = [c for i, c in enumerate(clusters) if i not in (a, b)]
        std = np.sqrt(np.mean(sum(s * value[m] for m, s in zip(*merged)) ** 2))
        err = np.sqrt(max(float(merged[1] @ cov[np.ix_(merged[0], merged[0])] @ merged[1]), 0.0))
        (done if std >= DETERMINED_SIGMAS * err else clusters).append(merged)
    return done + [c for c in clusters if len(c[0]) > 1]


def _max_offdiag(corr, members) -> float:
    sub = np.abs(corr[np.ix_(members, members)])
    np.fill_diagonal(sub, 0.0)
    return float(sub.max())


def _flat(entries) -> dict:
    """Determined entries as name -> number (groups named by their members joined with '+')."""
    out = {}
    kept = [e["deflection_std_deg"] for e in entries if e["kind"] in ("determined", "group")]
    if len(entries) > 1 and kept:
        out["largest_determined_deflection_std_deg"] = max(kept)
    for e in entries:
        if e["kind"] not in ("determined", "group"):
            continue
        name = "+".join(e["places"])
        out[f"{name}_deflection_std_deg"] = e["deflection_std_deg"]
        out[f"{name}_deflection_std_err_deg"] = e["standard_error_deg"]
        if "stiffness_Nm_per_rad" in e:
            out[f"{name}_stiffness_Nm_per_rad"] = e["stiffness_Nm_per_rad"]
            out[f"{name}_stiffness_err_Nm_per_rad"] = e["stiffness_standard_error_Nm_per_rad"]
    return out


def describe(entries) -> list[str]:
    """The entries in words, one line each, for the text report."""
    lines = []
    for e in entries:
        size = f"{e['deflection_std_deg']:.3g} +- {e['standard_error_deg']:.2g} deg"
        names = " ".join(n if n.startswith("-") else f"+{n}" for n in e["places"]).lstrip("+")
        if e["kind"] == "determined":
            line = f"  {names}: deflection {size} (std over the poses)"
            if "stiffness_Nm_per_rad" in e:
                line += (f", stiffness {e['stiffness_Nm_per_rad']:.4g} +- "
                         f"{e['stiffness_standard_error_Nm_per_rad']:.2g} N m/rad")
        elif e["kind"] == "group":
            line = (f"  {names}: only their combination is determined, {size} "
                    f"(each alone is not; |r| up to {e['max_abs_r']:.2f})")
        elif e["kind"] == "group, not determined":
            line = f"  {names}: not determined by these data, even combined ({size})"
        else:
            line = f"  {names}: not determined ({size}), below {e['below_deg']:.2g} deg"
        if "stiffness_above_Nm_per_rad" in e:
            line += f", stiffness above {e['stiffness_above_Nm_per_rad']:.3g} N m/rad"
        lines.append(line)
    return lines
