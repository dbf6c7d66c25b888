"""mkdocs hooks for aiohal's site (mkdocs.yml ``hooks``).

aiohal's docstrings name other objects with Sphinx roles (:meth:`x`, :class:`y`), which
mkdocstrings renders as written; the role's prefix is dropped from the page, leaving the name.
"""

from __future__ import annotations

import re

ROLE = re.compile(r":(?:meth|class|func|mod|attr|data|exc|obj):(?=<code)")


def on_page_content(html: str, **kwargs: object) -> str:
    return ROLE.sub("", html)
