"""HTML pieces of the report page: escaping, tables, figures, notes, Markdown, and the page shell.

Everything here is pure string building, so the page is byte-identical for the same inputs. The page has
no network resources: CSS is inline and every image is a relative link into ``assets/``. A short inline
script records, once the page has loaded, how many ``<img>`` elements decoded (``naturalWidth > 0``) as
attributes of ``<body>`` (``data-images-loaded``, ``data-images-total``, ``data-images-missing``), which
a headless browser can read back (``pipelines/report_browser.py``).
"""

from __future__ import annotations

import html
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass

CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 0 auto;
       max-width: 1280px; padding: 0 24px 48px; color: #1d2125; background: #fbfbfa; line-height: 1.45; }
h1 { margin: 24px 0 4px; } h2 { border-bottom: 1px solid #d5d7da; padding-bottom: 4px; margin-top: 36px; }
nav ol { columns: 2; padding-left: 20px; } nav a { text-decoration: none; }
table { border-collapse: collapse; margin: 8px 0 16px; font-size: 14px; }
th, td { border: 1px solid #d5d7da; padding: 3px 8px; text-align: left; vertical-align: top; }
th { background: #eef0f2; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
figure { margin: 12px 0 20px; } figcaption { font-size: 13px; color: #4a5057; margin-top: 4px; }
figure img { max-width: 100%; height: auto; border: 1px solid #d5d7da; background: #000; }
.note { border-left: 4px solid #c77700; background: #fff6e5; padding: 6px 10px; margin: 8px 0;
        font-size: 14px; }
.warnings { border-left-color: #b3261e; background: #fdecea; }
.muted { color: #5f666d; font-size: 13px; }
code { background: #eef0f2; padding: 0 3px; border-radius: 3px; }
details { margin: 8px 0; }
"""

# Runs after every image has either loaded or failed (the load event waits for both).
IMAGE_CHECK_SCRIPT = """
window.addEventListener("load", function () {
  var images = document.images, loaded = 0, missing = [];
  for (var i = 0; i < images.length; i++) {
    if (images[i].complete && images[i].naturalWidth > 0) { loaded++; }
    else { missing.push(images[i].getAttribute("src")); }
  }
  document.body.setAttribute("data-images-loaded", String(loaded));
  document.body.setAttribute("data-images-total", String(images.length));
  document.body.setAttribute("data-images-missing", missing.join(" "));
});
"""

NOT_PRODUCED = "not produced"


def esc(value: object) -> str:
    """Text (or any value via ``str``) escaped for HTML content and attribute values."""
    return html.escape(str(value), quote=True)


def slug(text: str, limit: int = 40) -> str:
    """A lowercase ``a-z0-9-`` name for file names and anchors (``"x"`` when nothing is left)."""
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")[:limit].strip("-") or "x"


def format_number(value: object) -> str:
    """Numbers rounded for display: ints as they are, floats to 4 significant digits (1 decimal from 1000)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return str(value)
    if isinstance(value, int):
        return str(value)
    if not math.isfinite(value):
        return str(value)
    if abs(value) >= 1000:
        return f"{value:,.1f}"
    return f"{value:.4g}"


def note(text: str, extra_class: str = "") -> str:
    """A visible boxed note (e.g. ``not produced: ...``); ``text`` is escaped."""
    classes = f"note {extra_class}".strip()
    return f'<p class="{classes}">{esc(text)}</p>\n'


def not_produced(what: str) -> str:
    """The note shown where an input is absent: ``not produced: <what>``."""
    return note(f"{NOT_PRODUCED}: {what}")


def table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """An HTML table; numbers are right-aligned and rounded with ``format_number``."""
    parts = ["<table>\n<thead><tr>", *(f"<th>{esc(h)}</th>" for h in header), "</tr></thead>\n<tbody>\n"]
    for row in rows:
        parts.append("<tr>")
        for cell in row:
            numeric = isinstance(cell, (int, float)) and not isinstance(cell, bool)
            css = ' class="num"' if numeric else ""
            parts.append(f"<td{css}>{esc(format_number(cell))}</td>")
        parts.append("</tr>\n")
    parts.append("</tbody>\n</table>\n")
    return "".join(parts)


def figure(src: str, caption: str, alt: str | None = None) -> str:
    """An image with a caption; ``src`` is a relative URL inside the report folder."""
    return (
        f'<figure><img src="{esc(src)}" alt="{esc(alt or caption)}">'
        f"<figcaption>{esc(caption)}</figcaption></figure>\n"
    )


@dataclass
class Section:
    """One ``<section>`` of the page: ``anchor`` is its id, ``body`` ready-made HTML."""

    anchor: str
    title: str
    body: str


def page(title: str, subtitle: str, sections: Sequence[Section], warnings: Sequence[str]) -> str:
    """The whole ``index.html``: heading, warnings box, table of contents, sections, image-check script."""
    toc = "".join(f'<li><a href="#{esc(s.anchor)}">{esc(s.title)}</a></li>' for s in sections)
    warning_box = ""
    if warnings:
        items = "".join(f"<li>{esc(w)}</li>" for w in warnings)
        warning_box = (
            f'<div class="note warnings" id="warnings"><strong>Warnings</strong><ul>{items}</ul></div>\n'
        )
    body = "".join(
        f'<section id="{esc(s.anchor)}">\n<h2>{esc(s.title)}</h2>\n{s.body}</section>\n' for s in sections
    )
    return (
        "<!DOCTYPE html>\n"
        '<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
        f"<title>{esc(title)}</title>\n<style>{CSS}</style>\n</head>\n<body>\n"
        f'<h1>{esc(title)}</h1>\n<p class="muted">{esc(subtitle)}</p>\n{warning_box}'
        f"<nav><strong>Contents</strong><ol>{toc}</ol></nav>\n{body}"
        f"<script>{IMAGE_CHECK_SCRIPT}</script>\n</body>\n</html>\n"
    )


def markdown_to_html(text: str) -> str:
    """Markdown (headings, paragraphs, pipe tables, lists, images, code) -> HTML, via Python-Markdown.

    The Markdown is data (an evaluation writes names from datasets into it), so raw HTML in it is shown
    as text, never passed through: a ``<script>`` or an ``onerror`` attribute cannot reach the page. Links
    are checked afterwards by :func:`rewrite_links`. Headings are shifted down two levels (``#`` becomes
    ``<h3>``) so an embedded document nests under its report section.
    """
    import markdown

    converter = markdown.Markdown(extensions=["tables", "fenced_code", "sane_lists"])
    # Without these two, Python-Markdown copies HTML blocks and inline tags verbatim.
    converter.preprocessors.deregister("html_block")
    converter.inlinePatterns.deregister("html")
    converted = converter.convert(text)
    return re.sub(
        r"<(/?)h([1-6])\b",
        lambda m: f"<{m.group(1)}h{min(6, int(m.group(2)) + 2)}",
        converted,
    )


_IMG_TAG = re.compile(r"<img\b[^>]*>", re.IGNORECASE)
_ATTRIBUTE = re.compile(r'\b(src|href)="([^"]*)"', re.IGNORECASE)
_EXTERNAL = re.compile(r"^[a-z][a-z0-9+.-]*:|^//|^#", re.IGNORECASE)
# External links that stay links; any other scheme (javascript:, data:, vbscript:, ...) loses its href.
_SAFE_LINK = re.compile(r"^(https?:|mailto:|#)", re.IGNORECASE)


def rewrite_links(
    fragment: str, resolve: Callable[[str], str | None], on_missing: Callable[[str], None]
) -> str:
    """Point the relative ``src``/``href`` links of an HTML fragment at copied assets.

    ``resolve(link)`` returns the new relative URL, or ``None`` when the target does not exist; then an
    image becomes a ``not produced`` note and a link loses its ``href``, and ``on_missing(link)`` is
    called. External images (``http:`` etc.) are replaced by a note, since the page loads nothing from
    the network; ``http(s):``, ``mailto:`` and ``#`` links stay as links, and a link of any other scheme
    (``javascript:`` ...) loses its ``href``.
    """

    def image(match: re.Match) -> str:
        tag = match.group(0)
        source = re.search(r'\bsrc="([^"]*)"', tag)
        if source is None:
            return tag
        link = html.unescape(source.group(1))
        if _EXTERNAL.match(link):
            on_missing(link)
            return f'<span class="note">{NOT_PRODUCED}: external image {esc(link)} is not embedded</span>'
        target = resolve(link)
        if target is None:
            on_missing(link)
            return f'<span class="note">{NOT_PRODUCED}: {esc(link)}</span>'
        return tag.replace(source.group(0), f'src="{esc(target)}"')

    def attribute(match: re.Match) -> str:
        name, link = match.group(1), html.unescape(match.group(2))
        if name.lower() != "href" or _SAFE_LINK.match(link):
            return match.group(0)
        if _EXTERNAL.match(link):
            return f'data-refused="{esc(link)}"'
        target = resolve(link)
        if target is None:
            on_missing(link)
            return f'data-missing="{esc(link)}"'
        return f'href="{esc(target)}"'

    fragment = _IMG_TAG.sub(image, fragment)
    # Only <a href> remains to rewrite; image tags are already done (their src is not matched again
    # because attribute() leaves src alone).
    return _ATTRIBUTE.sub(attribute, fragment)
