"""The report as one self-contained HTML page (``index.html``): figures embedded as base64 PNGs, tables as HTML
tables, nothing from the network."""

from __future__ import annotations

import base64
import html
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

INDEX_HTML = "index.html"
"""The report's page."""

_STYLE = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; margin: 1.5em auto; max-width: 1400px;
       padding: 0 1em; color: #222; line-height: 1.4; }
h1 { font-size: 1.5em; } h2 { font-size: 1.25em; border-bottom: 1px solid #ccc; margin-top: 2em; }
h3 { font-size: 1.05em; margin-top: 1.5em; }
table { border-collapse: collapse; margin: 0.6em 0 1em 0; font-size: 0.85em; }
th, td { border: 1px solid #bbb; padding: 0.25em 0.6em; text-align: right; }
th { background: #f0f0f0; } td:first-child, th:first-child { text-align: left; } td { white-space: nowrap; }
table.settings td { text-align: left; white-space: normal; overflow-wrap: anywhere; }
table.settings td:first-child { white-space: nowrap; } table.settings { max-width: 100%; }
.scroll { overflow-x: auto; max-width: 100%; }
figure { margin: 1em 0; } figure img { max-width: 100%; height: auto; border: 1px solid #eee; }
figcaption { font-size: 0.85em; color: #444; max-width: 1100px; }
nav ul { columns: 2; font-size: 0.9em; } .note { font-size: 0.85em; color: #444; }
pre { background: #f6f6f6; padding: 0.6em; white-space: pre-wrap; font-size: 0.8em; }
"""


@dataclass
class Section:
    """One section of the page: its heading (and entry in the table of contents) and its HTML fragments."""

    title: str
    parts: list[str] = field(default_factory=list)

    @property
    def anchor(self) -> str:
        """The section's id in the page."""
        return "".join(c if c.isalnum() else "-" for c in self.title.lower()).strip("-")


def paragraph(text: str, css_class: str | None = None, tag: str = "p") -> str:
    """:return: the escaped text in ``<tag>`` (``p``, ``h3``, ``pre``...)"""
    attribute = f' class="{css_class}"' if css_class else ""
    return f"<{tag}{attribute}>{html.escape(text)}</{tag}>"


def bullet_list(items: Iterable[str]) -> str:
    """:return: ``<ul>`` of escaped items"""
    return "<ul>" + "".join(f"<li>{html.escape(item)}</li>" for item in items) + "</ul>"


def figure(png: str | Path, caption: str) -> str:
    """:return: ``<figure>`` with the PNG file ``png`` embedded as base64 and ``caption`` (also its alt text)"""
    data = base64.b64encode(Path(png).read_bytes()).decode("ascii")
    alt = html.escape(caption, quote=True)
    return (
        f'<figure><img alt="{alt}" src="data:image/png;base64,{data}">'
        f"<figcaption>{html.escape(caption)}</figcaption></figure>"
    )


def _cell(value: Any) -> str:
    if value is None or value == "" or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) >= 10_000:
        return f"{value:,}"
    return str(value)


def table(
    header: Sequence[str], rows: Iterable[Sequence[Any]], caption: str | None = None, css_class: str | None = None
) -> str:
    """:return: ``<table>`` in a horizontally scrolling ``<div>`` (cells ``None``, ``""`` and nan shown as ``-``,
    floats with 4 significant digits)"""
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(_cell(c))}</td>" for c in row) + "</tr>" for row in rows)
    title = f"<caption>{html.escape(caption)}</caption>" if caption else ""
    attribute = f' class="{css_class}"' if css_class else ""
    table_ = f"<table{attribute}>{title}<thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"
    return f'<div class="scroll">{table_}</div>'


def dict_table(rows: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> str:
    """:return: :func:`table` of dict rows"""
    return table(columns, [[row.get(c) for c in columns] for row in rows])


def settings_table(settings: Mapping[str, Any], caption: str | None = None) -> str:
    """:return: a two-column table ``setting | value`` (nested values as compact JSON, long values wrapped)"""
    rows = [
        (key, value if isinstance(value, (str, int, float)) else json.dumps(value)) for key, value in settings.items()
    ]
    return table(("setting", "value"), rows, caption, "settings")


def html_page(title: str, sections: Sequence[Section], subtitle: str | None = None) -> str:
    """:return: the HTML document: ``title``, ``subtitle``, a table of contents, then the ``sections``"""
    created = datetime.now(UTC).isoformat(timespec="seconds")
    contents = "".join(f'<li><a href="#{s.anchor}">{html.escape(s.title)}</a></li>' for s in sections)
    body = "".join(
        f'<section id="{s.anchor}"><h2>{html.escape(s.title)}</h2>{"".join(s.parts)}</section>' for s in sections
    )
    line = paragraph(subtitle, "note") if subtitle else ""
    return (
        "<!DOCTYPE html>\n"
        f'<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
        f"<style>{_STYLE}</style></head><body><h1>{html.escape(title)}</h1>{line}"
        f'<p class="note">Written {created} by sb3-collapse; self-contained (images embedded).</p>'
        f"<nav><ul>{contents}</ul></nav>{body}</body></html>\n"
    )
