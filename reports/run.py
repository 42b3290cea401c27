"""A run's report a person can read: the measurements drawn against the fitted geometry (the
routine's :class:`~cellcal.routines.framework.drawing.Drawing`), the frame before and after, the gates,
the residual of every measurement, and the routine's own numbers; one HTML page with its plots.
"""
from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from cellcal.reports.page import figure_html, plt, write_page
from cellcal.reports.trend import TREND_IMAGE, TREND_PAGE
from cellcal.solvers.geometry import se3
from cellcal.routines.framework import tool_frame
from cellcal.routines.framework.base import FRAME_KEYS, Result, RunEnding, tool_frame_json
from cellcal.routines.framework.drawing import Drawing

STYLES = {"measured": dict(ls="none", marker=".", ms=5), "fitted": dict(ls="-", lw=1.2, color="0.25")}


def _frame_row(label: str, pose, lean: bool = True) -> str:
    """One frame's row: x, y, z (mm), its rotation vector (deg) and, for a tool frame (`lean`),
    how its z axis leans toward the flange's x and y (deg: what ``axis_tilt_x_deg`` /
    ``axis_tilt_y_deg`` count for a tool drawn along the flange's z)."""
    if pose is None:
        return f"<tr><th>{label}</th><td colspan=8>none</td></tr>"
    f = tool_frame_json(pose)
    cells = "".join(f"<td>{f[k]:.4f}</td>" for k in FRAME_KEYS)
    leans = "".join(f"<td>{v:.4f}</td>" for v in np.degrees(se3.z_axis_lean(np.asarray(pose, dtype=float)[3:]))) \
        if lean else "<td></td><td></td>"
    return f"<tr><th>{label}</th>{cells}{leans}</tr>"


def _draw(drawing: Drawing, path: Path) -> None:
    """The drawing's panels side by side; the cell file's geometry dashed (a cross for one point)."""
    n = len(drawing.panels)
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n + 0.6, 4.4), squeeze=False)
    for ax, panel in zip(axes[0], drawing.panels):
        for layer in panel.layers:
            xy = np.asarray(layer.xy, dtype=float).reshape(-1, 2)
            style = STYLES.get(layer.kind) or (dict(ls="none", marker="x", ms=9, color="tab:red") if len(xy) == 1
                                               else dict(ls="--", lw=1, color="tab:red"))
            if layer.paired and ax.lines:
                style = {**style, "color": ax.lines[-1].get_color()}
            ax.plot(xy[:, 0], xy[:, 1], label=layer.label, **style)
        if panel.equal_axes:
            ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(panel.title, fontsize=10)
        ax.set_xlabel(panel.xlabel)
        ax.set_ylabel(panel.ylabel)
        ax.legend(fontsize=7)
    fig.subplots_adjust(left=0.7 / fig.get_figwidth(), right=0.98, bottom=0.12, top=0.92, wspace=0.3)  # as above
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _trend_link(folder: Path, result: Result, tool_id: int) -> str:
    """The tool's trend plot and a link to its page (the service's STATE/reports/tool-ID/, beside
    this run's folder), when the run measured the tool and the page is there."""
    page = folder / f"tool-{tool_id}" / TREND_PAGE
    if result.tool_frame is None or not page.is_file():
        return ""
    where = f"../tool-{tool_id}/"
    return (f"<h2>Drift history of tool {tool_id}</h2>"
            + figure_html(where + TREND_IMAGE, f"tool {tool_id}: change against the last full calibration")
            + f"<p><a href='{where}{TREND_PAGE}'>the tool's trend page</a></p>")


CHECK_WORDS = {"ok": "Tool check OK: the tool is within its inner band",
               "corrected": "Tool check CORRECTED: the tool is beyond its inner band, within its outer one",
               "alarm": "Tool check ALARM", "drift": "Tool check DRIFT ALARM"}


def headline(result: Result, tool_id: int | None, ending: RunEnding | None) -> list[str]:
    """The report's first lines: what the run found (a check's verdict, else the gates) and what
    was written to the controller; without `ending` (a result reported outside the service), the
    gates only."""
    if result.verdict is not None:
        found = CHECK_WORDS.get(str(result.verdict), f"Tool check: {result.verdict}")
    elif result.passed_gates:
        found = "Every gate passed"
    else:
        found = "A gate failed: " + "; ".join(result.reasons())
    if ending is None:
        return [found]
    if ending.wrote:
        tool = "" if tool_id is None else f" as tool {tool_id}'s frame"
        written = f"The tool frame found was written to the controller{tool} and read back."
    else:
        written = "Nothing was written to the controller."
    return [found, written, f"The run ended {ending.code_name}: {ending.reason}"]


def write_run_report(folder: str | Path, run_id: int, result: Result, tool_id: int | None = 1,
                     ending: RunEnding | None = None) -> Path:
    """The run's page into FOLDER/run-RUN_ID/, naming the tool `tool_id` the run was for (None: the
    cell describes none), its `ending` at the top (see :func:`headline`), with that tool's trend
    where FOLDER has it."""
    out = Path(folder) / f"run-{run_id}"
    out.mkdir(parents=True, exist_ok=True)
    residuals = np.asarray(result.residuals_mm, dtype=float)
    per = np.linalg.norm(residuals.reshape(len(residuals), -1), axis=1) if residuals.size else residuals
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.6))
    ax1.plot(np.arange(1, len(per) + 1), per, ".", ms=4)
    ax1.axhline(result.expected_noise_mm, color="tab:red", lw=1, label="expected noise")
    ax1.set_xlabel("measurement, in the order taken")
    ax1.set_ylabel("residual (mm)")
    ax1.legend()
    ax2.hist(per, bins=30)
    ax2.set_xlabel("residual (mm)")
    fig.suptitle(f"run {run_id}: {result.routine}, residual RMS {result.residual_rms_mm:.4f} mm")
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.14, top=0.88, wspace=0.25)  # no layout pass: cheaper
    fig.savefig(out / "residuals.png", dpi=100)
    plt.close(fig)

    drawing = ""
    if result.drawing is not None:
        _draw(result.drawing, out / "drawing.png")
        caption = html.escape(result.drawing.caption + " Panels: "
                              + "; ".join(panel.title for panel in result.drawing.panels) + ".")
        drawing = (f"<h2>Measurements against the fitted geometry</h2><figure><img src='drawing.png' "
                   f"alt='{caption}'><figcaption>{caption}</figcaption></figure>")
    before = result.tool_frame_before
    frame = result.frame or {}
    base_row = _frame_row(f"{frame['to']} in the {frame['from']} frame, found", frame["pose_m_rad"], lean=False) \
        if {"to", "from", "pose_m_rad"} <= set(frame) else ""
    determined = (f"<p>This run determined {html.escape(tool_frame.described(result.determines))} of the tool "
                  "frame; the rest is kept from the controller's frame before the run (the notes say where it "
                  "came from).</p>" if result.tool_frame is not None else "")
    gates = "".join(f"<tr><td>{'pass' if g.passed else '<b>FAIL</b>'}</td><td>{html.escape(g.name)}</td>"
                    f"<td>{html.escape(g.why)}</td></tr>" for g in result.gates)
    params = "".join(f"<tr><td>{html.escape(p.name)}</td><td>{p.value:.5g}</td>"
                     f"<td>{'' if p.std is None else f'{p.std:.3g}'}</td><td>{html.escape(p.unit)}</td></tr>"
                     for p in result.parameters)
    lines = headline(result, tool_id, ending)
    return write_page(
        out / "report.html", "cellcal run",
        f"<h1>Run {run_id}: {html.escape(result.routine)}</h1>"
        f"<p>{'no tool (the cell describes none)' if tool_id is None else f'tool {tool_id}'}</p>"
        f"<p><b>{html.escape(lines[0])}</b></p>" + "".join(f"<p>{html.escape(t)}</p>" for t in lines[1:])
        + drawing +
        "<h2>Tool frame</h2><table border=1 cellpadding=4><tr><th></th><th>x mm</th><th>y mm</th><th>z mm</th>"
        "<th>rx deg</th><th>ry deg</th><th>rz deg</th><th>z leans toward x, deg</th><th>toward y, deg</th></tr>"
        + _frame_row("before", before) + _frame_row("found", result.tool_frame) + base_row + "</table>"
        "<p>rx, ry, rz: the rotation vector (flange to tool frame); a lean of the z axis toward x is a turn "
        "about y.</p>" + determined +
        f"<h2>Gates</h2><table border=1 cellpadding=4>{gates}</table>"
        f"<h2>Parameters</h2><table border=1 cellpadding=4>{params}</table>"
        "<h2>Residuals</h2><img src='residuals.png' alt='residual of every measurement'>"
        + ("" if tool_id is None else _trend_link(Path(folder), result, tool_id))
        + "".join(f"<p>{html.escape(n)}</p>" for n in result.notes)
        + f"<h2>Everything</h2><pre>{html.escape(json.dumps(result.as_json(), indent=1, default=_plain))}</pre>"
        f"<p>dataset: {html.escape(str(result.dataset))}</p>")


def _plain(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    return str(value)
