"""A griffe extension for the API pages: Sphinx roles in docstrings become inline code.

The docstrings are numpydoc and sometimes name other objects with Sphinx roles
(``:func:`hsiffc.leakage.model.response```); mkdocstrings renders Markdown, so without this the roles
would show literally. ``:role:`~a.b.c``` becomes `` `c` `` and ``:role:`a.b.c``` `` `a.b.c` ``.
A reStructuredText literal-block marker (a paragraph ending in ``::`` before an indented block)
becomes a single colon: the indented block is already a code block in Markdown.
"""

from __future__ import annotations

import re

from griffe import Extension

ROLE = re.compile(r":(?:py:)?(?:func|class|meth|mod|attr|data|exc|obj|const):`(~?)([^`]+)`")
LITERAL = re.compile(r"(\S)::\n(?=\s*\n)")


def _code(match: re.Match) -> str:
    tilde, target = match.groups()
    return f"`{target.rsplit('.', 1)[-1] if tilde else target}`"


class SphinxRolesToCode(Extension):
    """Rewrite Sphinx roles in every docstring griffe loads."""

    def on_object(self, *, obj, **kwargs) -> None:  # noqa: ARG002 (griffe hook signature)
        if obj.docstring is not None and ":" in obj.docstring.value:
            obj.docstring.value = LITERAL.sub(r"\1:\n", ROLE.sub(_code, obj.docstring.value))
