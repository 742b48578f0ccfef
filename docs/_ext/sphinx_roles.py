"""A griffe extension: the Sphinx roles in safelane's docstrings become mkdocstrings cross-references.

safelane's docstrings write ``:class:`safelane.x.Y``` and ``:func:`evaluate``` (Sphinx roles), which
Markdown would show literally. Once the package is loaded, every role is rewritten into an autorefs
cross-reference to the object's full path (a name without dots is looked up from the docstring's own
scope outwards: class, module, parent modules). The cross-reference is optional: a target the API
reference does not render (a private helper) stays plain code instead of failing the strict build,
while every hand-written link on the site is still checked.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:class|func|meth|mod|data|attr|exc|obj):`~?([^`]+)`")


def _resolve(pkg: griffe.Module, path: str) -> str | None:
    """The path of the object ``path`` names in ``pkg`` (an imported name: the original's), or None."""
    if path == pkg.path:
        return path
    if not path.startswith(pkg.path + "."):
        return None
    try:
        member = pkg[path.removeprefix(pkg.path + ".")]
        return member.final_target.path if member.is_alias else member.path
    except (KeyError, griffe.AliasResolutionError, griffe.CyclicAliasError):
        return None


def _target(name: str, obj: griffe.Object, pkg: griffe.Module) -> str:
    """The full path ``name`` means in the docstring of ``obj``."""
    if name.startswith(pkg.path):
        return _resolve(pkg, name) or name
    scope: Any = obj if obj.is_module or obj.is_class else obj.parent
    while scope is not None:
        if found := _resolve(pkg, f"{scope.path}.{name}"):
            return found
        scope = scope.parent
    return name


def rewrite(text: str, obj: griffe.Object, pkg: griffe.Module) -> str:
    """``text`` with every Sphinx role replaced by an optional cross-reference."""

    def link(match: re.Match[str]) -> str:
        name = match.group(1).removesuffix("()")
        return f'<autoref identifier="{_target(name, obj, pkg)}" optional><code>{name}</code></autoref>'

    return ROLE.sub(link, text)


def _walk(obj: griffe.Object):
    yield obj
    for member in obj.members.values():
        if not member.is_alias:
            yield from _walk(member)


class SphinxRoles(griffe.Extension):
    """Rewrite the Sphinx roles of every docstring of a loaded package."""

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        """Called by griffe once the whole package is loaded."""
        for obj in _walk(pkg):
            if obj.docstring is not None:
                obj.docstring.value = rewrite(obj.docstring.value, obj, pkg)
