"""A tool's trend page: how far every measured frame of the tool (full calibrations and checks)
is from the first and from the last full calibration, tip (mm) and axis (deg), over time and
runs, with the fitted rates. Draws the object ``cellcal tool trend --json`` prints
(:func:`cellcal.daemon.drift.trend`); written by ``tool trend --report DIR`` and by the
service into STATE/reports/tool-ID/trend.html after every run that measured the tool."""
from __future__ import annotations

import html
import time
from pathlib import Path

from cellcal.reports.page import figure_html, plt, write_page

TREND_PAGE = "trend.html"
TREND_IMAGE = "trend.png"
MARKERS = {"calibration": dict(marker="s", ms=6), "check": dict(marker=".", ms=7)}


def _when(at: float) -> str:
    """Local time with its UTC offset (the status page writes times alike)."""
    local = time.localtime(at)
    offset = time.strftime("%z", local)  # +0100
    return time.strftime("%Y-%m-%d %H:%M", local) + f" UTC{offset[:3]}:{offset[3:]}"


def _number(value, unit: str) -> str:
    return "-" if value is None else f"{value:.4f} {unit}"


def _draw(trend: dict, path: Path) -> None:
    """Two panels (tip mm, axis deg) of the change against the last full calibration over the
    runs; full calibrations as squares, checks as dots."""
    points = trend["points"]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for ax, key, unit in ((axes[0], "tip_mm", "mm"), (axes[1], "axis_deg", "deg")):
        for kind, style in MARKERS.items():
            xy = [(p["run_id"], p["since_last_calibration"][key]) for p in points
                  if p["kind"] == kind and p["since_last_calibration"][key] is not None]
            if xy:
                ax.plot(*zip(*xy), ls="none", label=kind, **style)
        first = [(p["run_id"], p["since_first_calibration"][key]) for p in points
                 if p["since_first_calibration"][key] is not None]
        if first:
            ax.plot(*zip(*first), ls="-", lw=0.8, color="0.5", label="since the first calibration")
        ax.set_xlabel("run")
        ax.set_ylabel(f"{key.split('_')[0]} change ({unit})")
        ax.set_title(f"{key.split('_')[0]}: since the last full calibration", fontsize=10)
        if ax.lines:
            ax.legend(fontsize=7)
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.14, top=0.88, wspace=0.25)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_trend_page(folder: str | Path, trend: dict) -> Path:
    """The page (and its plot) for one tool's trend into `folder`; returns the page's path."""
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    _draw(trend, out / TREND_IMAGE)
    rate = trend["rate"]
    last = trend["last_calibration"]
    head = ("<p><b>Never calibrated here</b>: every point is a check against the controller's frame.</p>"
            if trend["never_calibrated"] else
            f"<p>First full calibration: run {trend['first_calibration']['run_id']} "
            f"({_when(trend['first_calibration']['at'])}); last: run {last['run_id']} ({_when(last['at'])}).</p>")
    rates = (f"<p>Rate since the last full calibration ({rate['points']} points; {html.escape(rate['fitted'])}): "
             f"tip {_number(rate['tip_mm_per_week'], 'mm')} per week, {_number(rate['tip_mm_per_1000_runs'], 'mm')} "
             f"per 1000 runs; axis {_number(rate['axis_deg_per_week'], 'deg')} per week, "
             f"{_number(rate['axis_deg_per_1000_runs'], 'deg')} per 1000 runs"
             + (f" ({html.escape(rate['why_none'])})" if rate["why_none"] else "") + ".</p>")
    rows = "".join(
        f"<tr><td>{p['run_id']}</td><td>{_when(p['at'])}</td><td>{html.escape(p['kind'])}</td>"
        f"<td>{html.escape(p['routine'])}</td><td>{'yes' if p['written'] else 'no'}</td>"
        f"<td>{_number(p['since_first_calibration']['tip_mm'], 'mm')}</td>"
        f"<td>{_number(p['since_first_calibration']['axis_deg'], 'deg')}</td>"
        f"<td>{_number(p['since_last_calibration']['tip_mm'], 'mm')}</td>"
        f"<td>{_number(p['since_last_calibration']['axis_deg'], 'deg')}</td></tr>" for p in trend["points"])
    return write_page(
        out / TREND_PAGE, f"cellcal tool {trend['tool_id']} trend",
        f"<h1>Tool {trend['tool_id']}: drift history</h1>" + head + rates
        + figure_html(TREND_IMAGE, "change of the tip and of the axis against the last full calibration (squares: "
                                   "full calibrations, dots: checks; line: against the first calibration)")
        + "<table border=1 cellpadding=4><tr><th>run</th><th>at</th><th>kind</th><th>routine</th><th>written</th>"
          "<th>tip since first</th><th>axis since first</th><th>tip since last calibration</th>"
          "<th>axis since last calibration</th></tr>" + rows + "</table>"
          "<p>A point compares only what its run determined (-: not determined, or no calibration to compare "
          "with).</p>")
