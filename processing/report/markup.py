"""The HTML pieces of the reports: notes, tables, embedded images, figures, the style sheet."""

from __future__ import annotations

import base64
import html
import logging
import math
from concurrent.futures import Executor, Future
from pathlib import Path

from matplotlib.figure import Figure

from processing.report.drawing import encode_rgb_png, figure_pixels, figure_png

log = logging.getLogger("mirrorgonio.processing")


def html_note(text: str) -> str:
    return f'<p class="note">{html.escape(text)}</p>'


def html_table(header: list[str] | None, rows: list[list[str]]) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header) if header else ""
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows)
    return (f"<table><thead><tr>{head}</tr></thead>" if head else "<table>") + f"<tbody>{body}</tbody></table>"


def embedded_img(png: bytes, alt: str, cls: str = "") -> str:
    data = base64.b64encode(png).decode("ascii")
    extra = f' class="{cls}"' if cls else ""
    return f'<img src="data:image/png;base64,{data}" alt="{html.escape(alt)}"{extra}>'


def figure_html(fig: Figure, alt: str, caption: str, encoder: FigureEncoder | None = None) -> str:
    if encoder is not None:
        return encoder.figure(fig, alt, caption)
    return f"<figure>{embedded_img(figure_png(fig), alt)}<figcaption>{caption}</figcaption></figure>"


def in_mm(x: float) -> str:
    return f"{1e3 * x:.2f} mm" if math.isfinite(x) else "unknown"


CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; max-width: 1180px; margin: 1.5em auto;
       padding: 0 1em; color: #222; line-height: 1.4; }
h1 { font-size: 1.5em; margin-bottom: 0.2em; } h2 { font-size: 1.2em; margin-top: 2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left; }
th { background: #f2f2f2; } td { font-variant-numeric: tabular-nums; }
figure { margin: 0.8em 0; } figure img { max-width: 100%; }
figcaption, .caption { font-size: 0.92em; color: #444; max-width: 60em; }
.note { color: #7a4b00; background: #fff6e0; padding: 0.4em 0.7em; border-left: 3px solid #e0a000; }
.strip { display: flex; flex-wrap: wrap; gap: 0.6em; } .strip figure { margin: 0; }
.strip img { width: 180px; } .strip figcaption { text-align: center; }
.quality-suspect { color: #fff; background: #b00020; padding: 0.7em 1em; font-size: 1.05em; margin: 0.6em 0; }
.quality-ok { color: #1b5e20; background: #e8f5e9; padding: 0.3em 0.7em; border-left: 3px solid #2e7d32; }
"""


class FigureEncoder:
    """Encodes the figures' PNGs on a worker thread (the deflate releases the GIL) while the next
    figure is drawn: :meth:`figure` draws and returns the ``<figure>`` with a placeholder that
    :meth:`fill` replaces by the embedded image."""

    def __init__(self, pool: Executor) -> None:
        self.pool = pool
        self.pending: dict[str, tuple[Future[bytes], str]] = {}

    def figure(self, fig: Figure, alt: str, caption: str) -> str:
        token = f"\x00figure-{len(self.pending)}\x00"
        self.pending[token] = (self.pool.submit(encode_rgb_png, figure_pixels(fig)), alt)
        return f"<figure>{token}<figcaption>{caption}</figcaption></figure>"

    def fill(self, text: str) -> str:
        for token, (future, alt) in self.pending.items():
            if token in text:
                try:
                    image = embedded_img(future.result(), alt)
                except Exception as exc:  # noqa: BLE001 - a figure never stops the processing
                    log.warning("report: %s: %s", alt, exc, exc_info=True)
                    image = html_note(f"this figure could not be encoded: {type(exc).__name__}: {exc}")
                text = text.replace(token, image)
        return text


def write_page(path: Path, title: str, body: list[str], css: str = CSS) -> Path:
    """One self-contained HTML page (``title``, the style sheet, ``body``'s pieces), written
    whole: through a temporary file beside ``path``, so a reader never sees half a page."""
    page = (
        f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n<title>{html.escape(title)}</title>\n'
        f"<style>{css}</style>\n</head>\n<body>\n" + "\n".join(body) + "\n</body>\n</html>\n"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(page, encoding="utf-8")
    tmp.replace(path)
    return path
