"""Render the document model as Markdown (figures linked beside it) and as self-contained HTML (figures inline).

Text is plain with `code` spans between backticks; both renderers escape everything else.
"""

from __future__ import annotations

import base64
import html
import re

from .document import Block, Bullets, Cell, Code, Figure, Heading, Paragraph, Table

_MD_SPECIAL = re.compile(r"([\\*<])")

_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; margin: 2rem auto; max-width: 72rem;
       padding: 0 1rem; color: #1b1b1b; line-height: 1.45; }
h1, h2, h3, h4 { line-height: 1.2; }
h2 { border-bottom: 1px solid #ddd; padding-bottom: .2rem; margin-top: 2.5rem; }
table { border-collapse: collapse; margin: .6rem 0 .2rem; font-size: .9rem; }
th, td { border: 1px solid #ccc; padding: .25rem .6rem; }
th { background: #f3f3f3; }
td.num, th.num { text-align: right; font-variant-numeric: tabular-nums; }
.caption { font-size: .85rem; color: #555; margin: 0 0 1rem; }
figure { margin: 1rem 0 1.5rem; }
figure img { max-width: 100%; height: auto; border: 1px solid #eee; }
figcaption { font-size: .85rem; color: #555; }
details { margin: .3rem 0; }
summary { cursor: pointer; }
pre { background: #f7f7f7; padding: .6rem; overflow-x: auto; font-size: .8rem; }
code { background: #f3f3f3; padding: 0 .2rem; border-radius: 3px; }
"""


def _spans(text: str) -> list[tuple[str, bool]]:
    """Split text into (part, is_code) at backticks."""
    return [(part, index % 2 == 1) for index, part in enumerate(text.split("`")) if part]


def md_text(text: str, table: bool = False) -> str:
    """Markdown inline text: code spans kept, Markdown syntax elsewhere escaped (and `|` inside tables)."""
    out = []
    for part, code in _spans(text):
        if code:
            out.append(f"`{part}`")
        else:
            escaped = _MD_SPECIAL.sub(r"\\\1", part)
            out.append(escaped.replace("|", r"\|") if table else escaped)
    return "".join(out)


def html_text(text: str) -> str:
    """HTML inline text: escaped, code spans as <code>."""
    return "".join(f"<code>{html.escape(p)}</code>" if code else html.escape(p) for p, code in _spans(text))


def slug(text: str) -> str:
    """An id / file-name-safe version of `text`."""
    return re.sub(r"[^A-Za-z0-9_-]+", "-", text).strip("-").lower() or "section"


def _md_cell(cell: Cell) -> str:
    text = md_text(cell.text, table=True)
    return f"**{text}**" if cell.bold and cell.text else text


def _md_table(table: Table) -> str:
    numeric = table.numeric or (False,) * len(table.header)
    lines = ["| " + " | ".join(md_text(h, table=True) for h in table.header) + " |",
             "|" + "|".join("---:" if n else ":---" for n in numeric) + "|"]
    lines += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in table.rows]
    if table.caption:
        lines.append(f"\n*{md_text(table.caption)}*")
    return "\n".join(lines)


def _md_block(block: Block) -> str:
    """One block as Markdown."""
    if isinstance(block, Heading):
        return f"{'#' * block.level} {md_text(block.text)}"
    if isinstance(block, Paragraph):
        return md_text(block.text)
    if isinstance(block, Bullets):
        return "\n".join(f"- {md_text(item)}" for item in block.items)
    if isinstance(block, Table):
        return _md_table(block)
    if isinstance(block, Figure):
        return f"![{md_text(block.title)}]({block.path})\n\n*{md_text(block.caption)}*"
    fence = "````" if "```" in block.text else "```"
    return f"{md_text(block.summary)}\n\n{fence}{block.language}\n{block.text}\n{fence}"


def to_markdown(blocks: list[Block]) -> str:
    """The whole report as GitHub-flavoured Markdown."""
    return "\n\n".join(_md_block(block) for block in blocks) + "\n"


def _html_table(table: Table) -> str:
    numeric = table.numeric or (False,) * len(table.header)

    def cell(tag: str, content: str, num: bool) -> str:
        attribute = ' class="num"' if num else ""
        return f"<{tag}{attribute}>{content}</{tag}>"

    head = "".join(cell("th", html_text(h), n) for h, n in zip(table.header, numeric))
    body = "".join(
        "<tr>" + "".join(cell("td", f"<strong>{html_text(c.text)}</strong>" if c.bold else html_text(c.text), n)
                         for c, n in zip(row, numeric)) + "</tr>\n" for row in table.rows)
    caption = f'<p class="caption">{html_text(table.caption)}</p>' if table.caption else ""
    return f"<table>\n<thead><tr>{head}</tr></thead>\n<tbody>\n{body}</tbody>\n</table>\n{caption}"


def _html_block(block: Block) -> str:
    """One block as HTML."""
    if isinstance(block, Heading):
        anchor = f' id="{html.escape(block.anchor)}"' if block.anchor else ""
        return f"<h{block.level}{anchor}>{html_text(block.text)}</h{block.level}>"
    if isinstance(block, Paragraph):
        return f"<p>{html_text(block.text)}</p>"
    if isinstance(block, Bullets):
        return "<ul>\n" + "".join(f"<li>{html_text(item)}</li>\n" for item in block.items) + "</ul>"
    if isinstance(block, Table):
        return _html_table(block)
    if isinstance(block, Figure):
        data = base64.b64encode(block.png).decode("ascii")
        return (f'<figure><img src="data:image/png;base64,{data}" alt="{html.escape(block.title)}">'
                f"<figcaption>{html_text(block.caption)}</figcaption></figure>")
    assert isinstance(block, Code)
    return (f"<details><summary>{html_text(block.summary)}</summary>"
            f"<pre><code>{html.escape(block.text)}</code></pre></details>")


def to_html(blocks: list[Block], title: str) -> str:
    """The whole report as one self-contained HTML page (CSS inline, figures as base64 data URIs)."""
    body = "\n".join(_html_block(block) for block in blocks)
    return (f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
            f"<title>{html.escape(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n{body}\n</body>\n</html>\n")
