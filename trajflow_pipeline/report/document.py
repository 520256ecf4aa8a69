"""A small, format-neutral document model: the report is built once as blocks and rendered as Markdown and HTML.

Text in blocks is plain; a span between backticks is code (rendered as `code` / <code>). Renderers escape
everything else, so run names or user dataset names cannot break the markup.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Cell:
    """One table cell: its text and whether it is emphasised (the best value of its column)."""

    text: str
    bold: bool = False


@dataclass(frozen=True)
class Table:
    """A table with a header row; `numeric` marks right-aligned columns."""

    header: tuple[str, ...]
    rows: tuple[tuple[Cell, ...], ...]
    numeric: tuple[bool, ...] = ()
    caption: str = ""


@dataclass(frozen=True)
class Heading:
    """A section heading (level 1 is the document title)."""

    level: int
    text: str
    anchor: str = ""


@dataclass(frozen=True)
class Paragraph:
    """A paragraph of plain text."""

    text: str


@dataclass(frozen=True)
class Bullets:
    """An unordered list of plain-text items."""

    items: tuple[str, ...]


@dataclass(frozen=True)
class Figure:
    """A PNG figure: the file name relative to the report (Markdown links it), its bytes (HTML embeds them), a
    short title (the image's alt text) and the caption saying what it shows."""

    path: str
    png: bytes = field(repr=False)
    title: str
    caption: str


@dataclass(frozen=True)
class Code:
    """A block of code (config, provenance): fenced in Markdown, a collapsible <details> block in HTML."""

    text: str
    language: str
    summary: str


Block = Heading | Paragraph | Bullets | Table | Figure | Code
