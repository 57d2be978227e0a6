"""Help text of the commands: docstrings made plain text for ``--help`` (``pcc``, ``pcc bench``)."""

from __future__ import annotations

import re

_RST_ROLE = re.compile(r":(?:func|class|mod|meth|attr|data|exc):`~?([^`]+)`")


def plain_text(doc: str) -> str:
    """A docstring as a terminal shows it: a reStructuredText role (``:func:`name```) becomes
    its name, double backquotes are dropped."""
    return _RST_ROLE.sub(r"\1", doc).replace("``", "")
