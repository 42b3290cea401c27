"""Report plots of a periodic joint error (``cyclic_joint_error``): for each implicated joint the
residual against the joint's angle before and after, with the fitted error function over the
angles it is known on, and the periodogram of every scanned joint with the orders kept."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from cellcal.reports.page import plt

from cellcal.solvers.analysis.analyze import Finding
from cellcal.solvers.analysis.effects.cyclic_joint_error import PeriodicJointError
from cellcal.solvers.analysis.effects.periodic_spline import PeriodicSpline
from cellcal.solvers.identification.measurement_model import Layout, Observations, jacobian


def _along(v: np.ndarray, u: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(u, axis=1)
    return np.einsum("ni,ni->n", v, u) / np.where(n > 1e-12, n, np.inf)


def _fitted(err: dict):
    cover = tuple((np.deg2rad(lo), np.deg2rad(hi)) for lo, hi in err["coverage_deg"])
    if "spline_knots" in err:
        return PeriodicSpline(err["joint"], tuple(err["coef_rad"]), cover)
    return PeriodicJointError(err["joint"], tuple(err["orders"]), tuple(err["sin_rad"]), tuple(err["cos_rad"]), cover)


def describe(err: dict) -> str:
    """'orders [..]' or 'a periodic spline of K knots' for one fitted joint error."""
    return f"orders {err['orders']}" if "orders" in err else f"a periodic spline of {err['spline_knots']} knots"


def cyclic_plots(out: Path, model, obs: Observations, f: Finding, rows: np.ndarray) -> list[tuple[str, str]]:
    """Write the plots; (file name, title) of each."""
    images = []
    errors = (f.extended.details or {}).get("errors", [])
    sub = obs.subset(rows)
    _, _, jq = jacobian(Layout(model, obs.target_names), f.baseline.x, sub, with_joints=True)
    for err in errors:
        j = err["joint"] - 1
        u = jq[:, :, j]
        angle = np.rad2deg(sub.q[:, j])
        fig, ax = plt.subplots(figsize=(7.5, 4.5))
        ax.scatter(angle, -_along(f.baseline.residuals[rows], u), s=8, alpha=0.5, label="geometric model only")
        ax.scatter(angle, -_along(f.extended.residuals[rows], u), s=8, alpha=0.5, label="with the periodic error")
        ax.set_xlabel(f"joint {j + 1} angle (deg)")
        ax.set_ylabel(f"residual along joint {j + 1}'s direction of effect (mm)")
        curve = ax.twinx()
        grid = np.linspace(angle.min() - 10.0, angle.max() + 10.0, 2000)
        curve.plot(grid, np.rad2deg(_fitted(err).delta_rad(np.deg2rad(grid))), color="k", lw=0.8,
                   label="fitted error (0 outside coverage)")
        curve.set_ylabel("fitted joint error (deg)")
        ax.legend(loc="upper left", fontsize=8)
        curve.legend(loc="upper right", fontsize=8)
        ax.set_title(f"joint {j + 1}: {describe(err)}", fontsize=10)
        fig.tight_layout()
        name = f"cyclic_joint{j + 1}.png"
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        images.append((name, f"Residual against joint {j + 1}'s angle, before and after, and the fitted error"))
    spectra = next((t.extra["spectra"] for c in f.candidates for t in c.terms if "spectra" in t.extra), None)
    if spectra:
        kept = {e["joint"]: e.get("orders", []) for e in errors}
        fig, axes = plt.subplots(len(spectra), 1, figsize=(7.5, 1.6 * len(spectra) + 0.8), sharex=True, squeeze=False)
        for ax, (j, s) in zip(axes[:, 0], sorted(spectra.items())):
            ax.plot(s.orders, s.amplitude_deg, lw=0.8)
            for n in kept.get(j, []):
                ax.plot(n, s.amplitude_deg[n - 1], "o", color="tab:red", ms=4)
            ax.set_ylabel(f"joint {j}\n(deg)", fontsize=8)
        axes[-1, 0].set_xlabel("order (cycles per revolution); red: orders kept by cross-validation")
        axes[0, 0].set_title("periodogram of the geometric residual along each joint's direction of effect",
                             fontsize=10)
        fig.tight_layout()
        fig.savefig(out / "periodogram.png", dpi=110)
        plt.close(fig)
        images.append(("periodogram.png", "Periodogram: amplitude of each order alone, per joint"))
    return images
