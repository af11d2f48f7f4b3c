"""The pages' HTML from their templates (``pages/templates/*.html.j2``, package data).

Autoescape is on for every template: whatever a value holds (a subject's name, a figure read
from a report, a failure's reason) is shown as text, never as markup; what the page's own code
puts in as markup (the viewer's scripts) says so (:class:`markupsafe.Markup`). Data for a
script goes through ``tojson``, which leaves nothing that could close the script.
"""

from __future__ import annotations

from functools import cache

import jinja2


@cache
def _environment() -> jinja2.Environment:
    env = jinja2.Environment(
        loader=jinja2.PackageLoader("facecap.pages", "templates"), autoescape=True,
        undefined=jinja2.StrictUndefined, trim_blocks=True, lstrip_blocks=True,
        keep_trailing_newline=True)
    # tojson keeps the data's own order (its default sorts the keys).
    env.policies["json.dumps_kwargs"] = {}
    return env


def render(template: str, **context) -> bytes:
    """The page ``template`` (a file name in ``pages/templates``) makes of ``context``, as
    UTF-8."""
    return _environment().get_template(template).render(**context).encode("utf-8")
