"""The analysis as a person reads it: plots and a short page (``--report DIR``).

The main plot shows the residual along the direction the named effect moves the
target, against the regressor that drives it (gravity deflection, approach
direction, joint angle, temperature...), before and after the model is
extended: a cause is recognised at a glance when the "before" points follow the
regressor and the "after" points lie flat.
"""
from __future__ import annotations

import html
import os
from pathlib import Path

import numpy as np

from cellcal.reports.page import figure_html, plt, write_page
from cellcal.solvers.analysis.analyze import Finding
from cellcal.solvers.analysis.transfer import Transfer
from cellcal.solvers.identification.measurement_model import Layout, Observations, jacobian
from cellcal.solvers.geometry.se3 import rotvec_to_matrix


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v), where=n > 1e-12)


MAX_POINTS = 4000  # a scatter of more points draws no more information, only slower and larger files


def plotted_rows(n: int) -> np.ndarray:
    """The rows a scatter plot draws: all of them, or an even random sample of MAX_POINTS."""
    if n <= MAX_POINTS:
        return np.arange(n)
    return np.sort(np.random.default_rng(0).choice(n, MAX_POINTS, replace=False))


def _regressor(model, obs: Observations, f: Finding, rows: np.ndarray):
    """(x values, x label, unit direction per row) for the named effect, at the given rows."""
    named = f.extended
    term = named.terms[0]
    layout = Layout(model, obs.target_names)
    sub = obs.subset(rows)
    effect_mm = named.effect_mm[rows]
    _, jx, jq = jacobian(layout, f.baseline.x, sub, with_joints=True)
    if term.param_basis:  # trees: many joints sag together; show the sag along gravity
        b = f.baseline.x[layout.base]
        down = rotvec_to_matrix(b[3:]) @ model.gravity
        down = np.broadcast_to(down / np.linalg.norm(down), effect_mm.shape)
        return np.einsum("ni,ni->n", effect_mm, down), \
            "sag along gravity predicted by the elastic model (mm)", down
    joint = term.where.get("joint", (term.where.get("joints") or [None])[0])
    if term.cause == "thermal_drift":
        x = term.extra["dT"][rows]
        label = "temperature change (K)" if term.where.get("driver") == "temp_c" else "warm-up fraction"
        return x, label, _unit(term.cart_basis[rows, :, 0])
    if term.cause == "trigger_latency":
        speed = np.einsum("nij,nj->ni", jq, -term.joint_basis[rows].delta(np.ones(1)))
        return np.linalg.norm(speed, axis=1), "TCP speed at the trigger (mm/s)", _unit(speed)
    if term.cause == "parallel_axis_tilt":
        return np.rad2deg(sub.q[:, joint]), f"joint {joint + 1} angle (deg)", _unit(effect_mm)
    direction = _unit(jq[:, :, joint - 1])
    if term.cause == "joint_compliance":
        return np.rad2deg(named.joint_delta[rows, joint - 1]), \
            f"fitted gravity deflection of joint {joint} (deg, follows its gravity torque)", direction
    if term.cause == "backlash":
        s = np.sign(term.joint_basis[rows].delta(np.ones(1))[:, joint - 1])
        jitter = np.random.default_rng(0).uniform(-0.15, 0.15, len(s))
        return s + jitter, f"approach direction of joint {joint} (-1 / +1)", direction
    return np.rad2deg(sub.q[:, joint - 1]), f"joint {joint} angle (deg)", direction


def _validate_plot(out: Path, v: Transfer) -> tuple[str, str]:
    """The --validate data set's error per row, in its row order: geometry only, and with the carried effect."""
    fig, ax = plt.subplots(figsize=(7.5, 4.0))
    rows = np.arange(len(v.baseline_errors_mm))
    ax.plot(rows, v.baseline_errors_mm, ".", ms=4, alpha=0.7,
            label=f"geometry only, mean {v.baseline_mean_mm:.3f} mm")
    if v.extended_errors_mm is not None:
        ax.plot(rows, v.extended_errors_mm, ".", ms=4, alpha=0.7,
                label=f"with {v.carried}, mean {v.extended_mean_mm:.3f} mm")
    ax.set_xlabel("row of the validation data")
    ax.set_ylabel("error (mm)")
    ax.set_title("validation data: fitted on the analysed data, only frame and targets refitted"
                 + ("" if v.extended_errors_mm is not None else " (no effect named)"), fontsize=10)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "validate.png", dpi=110)
    plt.close(fig)
    return "validate.png", "Validation data: error per row, geometry only and with the effect"


REPORT_FILES = ("residual_vs_regressor.png", "heldout_histogram.png", "candidates.png", "validate.png", "report.md",
                "report.html")


def prepare_folder(folder) -> Path:
    """The report's folder, made if missing, with any earlier report's files removed (no
    stale plot of another run stays beside this one); other files are left alone.
    Raises OSError with the reason when the folder cannot be used."""
    out = Path(folder)
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"{out}: exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    if not os.access(out, os.W_OK | os.X_OK):
        raise PermissionError(f"{out}: not writable")
    for name in REPORT_FILES:
        (out / name).unlink(missing_ok=True)
    for stale in (*out.glob("cyclic_joint*.png"), out / "periodogram.png"):
        stale.unlink(missing_ok=True)
    return out


def write_report(folder, model, obs: Observations, f: Finding, text: str, validation: Transfer | None = None) -> Path:
    out = prepare_folder(folder)
    images = []

    if f.cause != "none":
        rows = plotted_rows(len(obs))
        x, xlabel, u = _regressor(model, obs, f, rows)
        before = -np.einsum("ni,ni->n", f.baseline.residuals[rows], u)  # measured - model, along the effect
        after = -np.einsum("ni,ni->n", f.extended.residuals[rows], u)
        fig, ax = plt.subplots(figsize=(7.5, 4.5))
        ax.scatter(x, before, s=10, alpha=0.6, label="geometric model only")
        ax.scatter(x, after, s=10, alpha=0.6, label=f"with {f.cause}")
        ax.axhline(0.0, color="0.4", lw=0.8)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("residual along the effect (mm)")
        sampled = f" ({len(rows)} of {len(obs)} measurements drawn)" if len(rows) < len(obs) else ""
        ax.set_title(f"{f.extended.label}: residual against its regressor{sampled}", fontsize=10)
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "residual_vs_regressor.png", dpi=110)
        plt.close(fig)
        images.append(("residual_vs_regressor.png", "Residual against the regressor of the named effect"))
    if f.cause == "cyclic_joint_error" or any(t.cause == "cyclic_joint_error" for c in f.candidates for t in c.terms):
        from cellcal.reports.cyclic import cyclic_plots

        images += cyclic_plots(out, model, obs, f, plotted_rows(len(obs)))

    fig, ax = plt.subplots(figsize=(7.5, 4.0))
    top = max(f.baseline.heldout_errors.max(), f.extended.heldout_errors.max(),
              f.undecided.heldout_errors.max() if f.undecided is not None else 0.0)
    bins = np.linspace(0.0, top, 40)
    ax.hist(f.baseline.heldout_errors, bins=bins, alpha=0.6, label=f"geometry only, mean "
            f"{f.baseline.heldout_mean_mm:.3f} mm")
    if f.cause != "none":
        ax.hist(f.extended.heldout_errors, bins=bins, alpha=0.6, label=f"with {f.cause}, mean "
                f"{f.extended.heldout_mean_mm:.3f} mm")
    elif f.undecided is not None:  # an effect whose cause these data cannot decide: what its best explanation does
        ax.hist(f.undecided.heldout_errors, bins=bins, alpha=0.6, label=f"with {f.undecided.label} (cause "
                f"undecided), mean {f.undecided.heldout_mean_mm:.3f} mm")
    ax.set_xlabel("held-out error (mm)")
    ax.set_ylabel("measurements")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "heldout_histogram.png", dpi=110)
    plt.close(fig)
    images.append(("heldout_histogram.png", "Held-out errors before and after"))

    shown = f.candidates[:12]
    fig, ax = plt.subplots(figsize=(7.5, 0.35 * len(shown) + 1.5))
    ax.barh([c.label for c in shown][::-1], [c.heldout_mean_mm for c in shown][::-1], color="tab:blue")
    ax.axvline(f.baseline.heldout_mean_mm, color="tab:red", lw=1.2, label="geometry only")
    ax.set_xlabel("held-out mean error (mm)")
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(out / "candidates.png", dpi=110)
    plt.close(fig)
    images.append(("candidates.png", "Candidates ranked by held-out error"))
    if validation is not None:
        images.append(_validate_plot(out, validation))

    md = ["# cellcal analyze", "", "```", text, "```", ""]
    md += [f"![{title}]({name})" for name, title in images]
    (out / "report.md").write_text("\n".join(md) + "\n", encoding="utf-8")
    body = [f"<h1>cellcal analyze</h1><pre>{html.escape(text)}</pre>"]
    body += [figure_html(name, title) for name, title in images]
    return write_page(out / "report.html", "cellcal analyze", "".join(body))
