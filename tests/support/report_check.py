"""A run's report read back: the routine's drawing is in it, as a PNG, with its captions."""
from __future__ import annotations

import numpy as np

from cellcal.reports.run import write_run_report


def assert_report_draws(result, folder, *captions: str) -> str:
    """Write the run's report; its page shows a non-empty PNG of the drawing and every caption."""
    return assert_page_draws(write_run_report(folder, 1, result), *captions)


def assert_page_draws(page, *captions: str) -> str:
    text = page.read_text(encoding="utf-8")
    png = (page.parent / "drawing.png").read_bytes()
    assert "<img src='drawing.png'" in text
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    for caption in ("Measurements against the fitted geometry", *captions):
        assert caption in text, caption
    return text


def layer(result, panel_title: str, label: str) -> np.ndarray:
    """The (N, 2) points of one layer of the result's drawing."""
    panel = next(p for p in result.drawing.panels if p.title == panel_title)
    return np.asarray(next(layer.xy for layer in panel.layers if layer.label == label), dtype=float)
