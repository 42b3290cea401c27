"""ISO 9283 results as a person reads them: one page, one column per case, with plots.

Cases side by side (e.g. before calibration, after, after compensation): AP and RP per
test pose as grouped bars, and each case's attained positions about their command
position, pose by pose, with the RP sphere's radius drawn around the barycentre.
"""
from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from cellcal.reports.page import figure_html, plt, write_page

FILES = ("iso9283_ap_rp.png", "iso9283_scatter.png", "iso9283.md", "iso9283.html")


def write_report(folder, cases, text: str) -> Path:
    """cases: (name, pose labels (N,), commanded (N, 3), attained (N, 3), PoseCharacteristics list,
    DistanceCharacteristics or None) each. Raises OSError when the folder cannot be written."""
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    for name in FILES:
        (out / name).unlink(missing_ok=True)
    labels = [p.pose for p in cases[0][4]]

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    width = 0.8 / len(cases)
    for k, (name, _, _, _, poses, _) in enumerate(cases):
        by = {p.pose: p for p in poses}
        x = np.arange(len(labels)) + (k - (len(cases) - 1) / 2) * width
        axes[0].bar(x, [by[lab].ap_mm if lab in by else 0 for lab in labels], width, label=name)
        axes[1].bar(x, [by[lab].rp_mm if lab in by else 0 for lab in labels], width, label=name)
    for ax, what in zip(axes, ("pose accuracy AP (mm)", "pose repeatability RP (mm)")):
        ax.set_xticks(np.arange(len(labels)), labels)
        ax.set_ylabel(what)
    axes[0].set_yscale("log")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / FILES[0], dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, len(cases), figsize=(4.2 * len(cases), 4.2), squeeze=False)
    for ax, (name, pose, commanded, attained, poses, _) in zip(axes[0], cases):
        deviation = attained - commanded
        for p in poses:
            rows = pose == p.pose
            ax.scatter(deviation[rows, 0], deviation[rows, 1], s=8, alpha=0.6, label=p.pose)
            bar = deviation[rows].mean(axis=0)
            ax.add_patch(plt.Circle((bar[0], bar[1]), p.rp_mm, fill=False, lw=0.8))
        ax.plot(0, 0, "k+", ms=12)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("attained - command, x (mm)")
        ax.set_ylabel("y (mm)")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / FILES[1], dpi=110)
    plt.close(fig)

    captions = ((FILES[0], "AP and RP per test pose, every case"),
                (FILES[1], "Attained positions about the command position (+), RP circle about each barycentre"))
    (out / FILES[2]).write_text("# ISO 9283 pose characteristics\n\n```\n" + text + "\n```\n\n"
                                + "\n".join(f"![{c}]({f})" for f, c in captions) + "\n", encoding="utf-8")
    figures = "".join(figure_html(f, c) for f, c in captions)
    return write_page(out / FILES[3], "ISO 9283", f"<h1>ISO 9283 pose characteristics</h1><pre>{html.escape(text)}</pre>"
                      + figures, width_em=70)
