"""The report page's view: jinja2 templates (report/templates/) filled with text prepared in Python.

The templates hold the page's markup and prose; the values they show arrive already formatted:
numbers as text with their digits, tables as rows of cells (Table), figures as inline SVG or data
URIs (Image). Autoescaping is on, so text from files (names, paths, messages) is escaped wherever a
template shows it; the only markup passed in is matplotlib's SVG and the templates' own output, marked
with Markup where it is made. A variable that a template names but its context lacks raises
(StrictUndefined) instead of leaving a blank.
"""

from __future__ import annotations

import base64
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import pandas as pd
from jinja2 import Environment, FileSystemLoader, StrictUndefined
from markupsafe import Markup

TEMPLATES_DIR = Path(__file__).parent / "templates"


@dataclass(frozen=True)
class Table:
    """A table as text: its column names and its rows of cells."""

    columns: list[str]
    rows: list[list[str]]


@dataclass(frozen=True)
class Image:
    """A figure to embed: inline SVG markup, or the source (a data URI) and alt text of an <img>."""

    svg: Markup | None = None
    src: str = ""
    alt: str = ""

    @classmethod
    def inline(cls, svg: str) -> Image:
        """matplotlib's SVG of a figure we drew, embedded as markup (its text is the figure's own)."""
        return cls(svg=Markup(svg))

    @classmethod
    def data_uri(cls, data: bytes, mime: str, alt: str) -> Image:
        """The bytes of a file as an <img> source: an SVG read from a file cannot run scripts this way."""
        return cls(src=f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}", alt=alt)


def table_of(frame: pd.DataFrame, number: Callable[[float], str] | None = None) -> Table:
    """The frame's columns and cells as text (cell_text, floats by `number`, default number_text), in its order."""
    return Table([str(column) for column in frame.columns],
                 [[cell_text(value, number) for value in row] for row in frame.itertuples(index=False, name=None)])


def cell_text(value, number: Callable[[float], str] | None = None) -> str:
    """A table cell: blank when missing, a float by `number` (default number_text), anything else as str()."""
    if value is None or (pd.api.types.is_scalar(value) and pd.isna(value)):
        return ""
    if pd.api.types.is_float(value):
        return (number or number_text)(float(value))
    return str(value)


def number_text(x: float) -> str:
    """4 significant digits, but large values (focal lengths, coordinates) to 0.1 without exponent."""
    return f"{x:.1f}" if 1e4 <= abs(x) < 1e9 else f"{x:.4g}"


def render(template: str, **context) -> Markup:
    """templates/<template> rendered with `context`; its output is markup (escaped where it showed values)."""
    return Markup(environment().get_template(template).render(**context))


@cache
def environment() -> Environment:
    """The templates' environment: autoescaped, a missing variable an error, block tags leave no blank lines."""
    return Environment(loader=FileSystemLoader(TEMPLATES_DIR), autoescape=True, undefined=StrictUndefined,
                       trim_blocks=True, lstrip_blocks=True, keep_trailing_newline=True)
