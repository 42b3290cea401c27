"""What every report shares: matplotlib drawing to files (the service has no screen, so the
backend is set here, once, before pyplot loads), and the one HTML page around the text and
figures."""
from __future__ import annotations

import html
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after the backend is chosen)

__all__ = ["plt", "figure_html", "write_page"]


def figure_html(image: str, caption: str) -> str:
    """One figure: the image file (beside the page) and its caption."""
    return (f"<figure><img src='{html.escape(image)}' alt='{html.escape(caption)}'>"
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def write_page(path: str | Path, title: str, body: str, width_em: int = 60) -> Path:
    """Write `body` (HTML, already escaped where it holds text) as a page titled `title`."""
    path = Path(path)
    path.write_text(f"<!doctype html><meta charset='utf-8'><title>{html.escape(title)}</title>"
                    f"<body style='font-family:sans-serif;max-width:{width_em}em'>{body}</body>\n",
                    encoding="utf-8")
    return path
