"""Markdown rendered from Jinja templates: the Hub cards (`hub_cards/`) and every report
(`lerobot_roboscape/templates/`, one template per kind of report). The text and its layout live in the template;
the caller passes the values, and filters for how a value is written."""

from collections.abc import Callable
from pathlib import Path

import jinja2

REPORTS = Path(__file__).parents[1] / "templates"


def number(value: float | None, spec: str = "{:.3f}") -> str:
    """A figure as the reports write it (`{{ x | number }}`, `{{ x | number("{:.1%}") }}`): "-" where it was not
    measured."""
    return "-" if value is None else spec.format(value)


def render(folder: Path, template: str, filters: dict[str, Callable] | None = None, **fields) -> str:
    """`folder/template` filled with `fields`. A block tag's line leaves no line behind (`+%}` keeps it), and the
    text keeps its final newline. StrictUndefined: a field the caller forgot is an error, not an empty line in a
    report or a card."""
    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(folder),
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
        keep_trailing_newline=True,
    )
    env.filters.update({"number": number} | (filters or {}))
    return env.get_template(template).render(**fields)


def render_report(template: str, filters: dict[str, Callable] | None = None, **fields) -> str:
    """A report template of `lerobot_roboscape/templates/` filled with `fields`."""
    return render(REPORTS, template, filters, **fields)
