"""Markdown rendered from Jinja templates: the Hub cards (`hub_cards/`) and the reports
(`lerobot_roboscape/pipeline/templates/`). The text and its layout live in the template; the caller passes the
values, and filters for how a value is written."""

from collections.abc import Callable
from pathlib import Path

import jinja2


def render(folder: Path, template: str, filters: dict[str, Callable] | None = None, **fields) -> str:
    """`folder/template` filled with `fields`. A block tag's line leaves no line behind, and the text keeps its
    final newline. StrictUndefined: a field the caller forgot is an error, not an empty line in a report or a
    card."""
    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(folder),
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
        keep_trailing_newline=True,
    )
    env.filters.update(filters or {})
    return env.get_template(template).render(**fields)
