"""A self-contained HTML page: plotly.js embedded once, inline (no CDN, opens offline from file://),
tables, text and the report's numbers as JSON (``<script type="application/json" id="report-data">``)."""

import html
import json

CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 0 auto; max-width: 1400px;
       padding: 0 18px 40px; color: #222; }
h1 { font-size: 21px; margin: 14px 0 4px; } h2 { font-size: 17px; margin: 26px 0 6px; border-bottom: 1px solid #ddd; }
p, li { font-size: 14px; line-height: 1.45; } .sub { color: #555; font-size: 13px; margin: 0 0 8px; }
table { border-collapse: collapse; font-size: 13px; margin: 6px 0 10px; }
th, td { border: 1px solid #ddd; padding: 3px 8px; text-align: right; } th { background: #f4f4f4; }
td:first-child, th:first-child { text-align: left; }
tr.flagged td { background: #fde0e0; } .warn { background: #fff4d6; border-left: 4px solid #e0a000;
  padding: 6px 10px; margin: 6px 0; font-size: 14px; } .ok { color: #2a7a2a; }
pre { background: #f7f7f7; padding: 8px; font-size: 12px; overflow-x: auto; }
.row { display: flex; flex-wrap: wrap; gap: 12px; } .row > div { flex: 1 1 520px; min-width: 0; }
details summary { cursor: pointer; font-size: 14px; }
"""


def esc(x) -> str:
    return html.escape(str(x))


def _attr(name, value) -> str:
    return f' {name}="{esc(value)}"' if value else ""


def fmt(x, spec=".3g") -> str:
    if x is None:
        return "–"
    try:
        return format(x, spec)
    except (TypeError, ValueError):
        return esc(x)


class Page:
    def __init__(self, title: str):
        self.title = title
        self.parts = []
        self._plotly_included = False

    def add(self, raw_html: str):
        self.parts.append(raw_html)

    def h2(self, text, anchor=None):
        self.add(f"<h2{_attr('id', anchor)}>{esc(text)}</h2>")

    def p(self, text, cls=None):
        self.add(f"<p{_attr('class', cls)}>{esc(text)}</p>")

    def table(self, header, rows, row_classes=None, raw=False):
        """``raw``: cells are already HTML."""
        cell = (lambda x: str(x)) if raw else esc
        out = ["<table><tr>" + "".join(f"<th>{esc(h)}</th>" for h in header) + "</tr>"]
        for i, r in enumerate(rows):
            cls = row_classes[i] if row_classes else ""
            out.append(f"<tr{_attr('class', cls)}>" + "".join(f"<td>{cell(x)}</td>" for x in r) + "</tr>")
        self.add("\n".join(out) + "</table>")

    def figure(self, fig, div_id=None) -> str:
        """The figure's div; plotly.js goes inline with the first figure of the page only."""
        part = fig.to_html(full_html=False, include_plotlyjs=not self._plotly_included, div_id=div_id,
                           config={"displaylogo": False, "responsive": True})
        self._plotly_included = True
        return part

    def data(self, obj):
        text = json.dumps(obj, allow_nan=False, default=float).replace("</", "<\\/")
        self.add(f'<script type="application/json" id="report-data">{text}</script>')

    def html(self) -> str:
        return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
                f"<title>{esc(self.title)}</title><style>{CSS}</style></head><body>\n"
                + "\n".join(self.parts) + "\n</body></html>\n")


def finite(x):
    """NaN/inf -> None, recursively (JSON has no NaN)."""
    if isinstance(x, float):
        return x if x == x and abs(x) != float("inf") else None
    if isinstance(x, dict):
        return {k: finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [finite(v) for v in x]
    return x
