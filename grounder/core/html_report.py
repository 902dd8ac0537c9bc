"""Self-contained HTML reports: matplotlib figures embedded as base64 PNG in one file, no external assets.

Usage::

    from grounder.core.html_report import Section, figure_to_data_uri, write_html_report

    fig = plt.figure(); ...
    write_html_report(out / "report.html", "Calibration", [
        Section(title="Fit", text="Training loss per evaluation.", figures=(fig,)),
        Section(title="Parameters", table=[["name", "value"], ["box.mass", "0.37"]]),
    ])

A section is a :class:`Section` or a plain dict with the same keys. Figures may be matplotlib figures or
``data:`` URIs made earlier with :func:`figure_to_data_uri`; figures passed in are closed after rendering.
"""

from __future__ import annotations

import base64
import html
import io
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from image2sim_common.outdir import write_text_atomic


def figure_to_data_uri(fig: Any, *, dpi: int = 100) -> str:
    """A matplotlib figure as a ``data:image/png;base64,...`` URI (the figure is left open)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


@dataclass(frozen=True, kw_only=True)
class Section:
    """One titled block of a report.

    Attributes:
        title: Heading.
        text: Paragraph(s) of plain text (escaped; blank lines separate paragraphs).
        table: Rows of cells, the first row is the header; cells are shown with ``str``.
        figures: matplotlib figures or ``data:`` URIs, shown in order.
    """

    title: str
    text: str = ""
    table: Sequence[Sequence[object]] = ()
    figures: Sequence[Any] = field(default_factory=tuple)


_STYLE = (
    "body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}"
    "table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}"
    "th{background:#f0f0f0}td:first-child,th:first-child{text-align:left}img{max-width:100%;margin:0.5em 0}"
)


def _as_section(section: Section | Mapping[str, Any]) -> Section:
    if isinstance(section, Section):
        return section
    return Section(**dict(section))


def render_html(title: str, sections: Sequence[Section | Mapping[str, Any]]) -> str:
    """The report as an HTML string (figures inlined)."""
    parts = [
        "<!DOCTYPE html>",
        '<html><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title><style>{_STYLE}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
    ]
    for raw in sections:
        section = _as_section(raw)
        parts.append(f"<h2>{html.escape(section.title)}</h2>")
        for paragraph in section.text.split("\n\n"):
            if paragraph.strip():
                parts.append(f"<p>{html.escape(paragraph.strip())}</p>")
        if section.table:
            header, *rows = section.table
            parts.append("<table><tr>" + "".join(f"<th>{html.escape(str(c))}</th>" for c in header) + "</tr>")
            for row in rows:
                parts.append("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>")
            parts.append("</table>")
        for fig in section.figures:
            if isinstance(fig, str):
                uri = fig
            else:
                import matplotlib.pyplot as plt

                uri = figure_to_data_uri(fig)
                plt.close(fig)
            parts.append(f'<img alt="{html.escape(section.title)}" src="{html.escape(uri)}">')
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"


def write_html_report(path: Path, title: str, sections: Sequence[Section | Mapping[str, Any]]) -> Path:
    """Writes one self-contained HTML file atomically (temporary file, then renamed). Returns ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(path, render_html(title, sections))
