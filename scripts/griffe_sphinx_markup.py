"""The reST of ajtwin's docstrings, read as the Markdown the documentation site renders.

The docstrings are numpydoc written for Sphinx (scikit-image's style): cross-references as
roles (``:func:`judge_run```, ``:class:`~ajtwin.model.limits.StateLimits```) and doctest
blocks anywhere in the text. mkdocstrings renders docstrings as Markdown, where a role is
literal text and a doctest block outside an *Examples* section runs into its paragraph. This
griffe extension, loaded by ``mkdocs.yml``, rewrites both once the package is loaded:

* a role whose target resolves in the object's scope (its module's names, then its parents')
  to a public object of ajtwin becomes a cross-reference ``[`title`][ajtwin.full.path]``; any other
  (NumPy, the standard library, a name that does not resolve) becomes plain code, so an
  unresolved name never fails the strict build for a target the site cannot hold;
* a run of ``>>>`` / ``...`` lines and their output becomes a ``pycon`` code block.
"""

from __future__ import annotations

import re

import griffe

ROLE = re.compile(r":(?:py:)?(func|class|meth|mod|data|attr|obj|exc|const):`(~?)([^`<>]+?)(\(\))?`")
DOCTEST_START = re.compile(r"^(\s*)>>> ")


def _lookup(root: griffe.Object, path: str) -> griffe.Object | None:
    """The ajtwin object at a dotted path, or None (outside ajtwin or missing)."""
    if path == root.path:
        return root
    if not path.startswith(root.path + "."):
        return None
    try:
        found = root[path[len(root.path) + 1 :]]
    except (KeyError, griffe.AliasResolutionError, griffe.CyclicAliasError):
        return None
    try:
        return found.final_target if found.is_alias else found
    except (griffe.AliasResolutionError, griffe.CyclicAliasError):
        return None


def _target(obj: griffe.Object, root: griffe.Object, name: str) -> str | None:
    """The full path of ``name`` as written in ``obj``'s docstring, if it is an ajtwin object."""
    name = name.lstrip(".")
    head, _, rest = name.partition(".")
    candidates = [name]
    scope = obj
    while scope is not None:  # the object's own scope, then its parents'
        try:
            candidates.append(".".join(filter(None, [scope.resolve(head), rest])))
        except (griffe.NameResolutionError, AttributeError):
            pass
        candidates.append(f"{scope.path}.{name}")
        scope = scope.parent
    for path in candidates:
        found = _lookup(root, path)
        if found is not None:
            # a private object has no page of its own: its name stays code
            private = any(part.startswith("_") for part in found.path.split("."))
            return None if private else found.path
    return None


def _roles(text: str, obj: griffe.Object, root: griffe.Object) -> str:
    def replace(match: re.Match) -> str:
        _, short, name, parens = match.groups()
        title = (name.rsplit(".", 1)[-1] if short else name) + (parens or "")
        target = _target(obj, root, name)
        return f"[`{title}`][{target}]" if target else f"`{title}`"

    return ROLE.sub(replace, text)


def _doctest_blocks(text: str) -> str:
    """Fence each doctest block (``>>>`` lines and their output, up to a blank line)."""
    lines, out, i = text.splitlines(), [], 0
    fenced = False
    while i < len(lines):
        line = lines[i]
        if line.lstrip().startswith("```"):
            fenced = not fenced
        match = None if fenced else DOCTEST_START.match(line)
        if not match:
            out.append(line)
            i += 1
            continue
        indent = match.group(1)
        block = []
        while i < len(lines) and lines[i].strip():
            block.append(lines[i].removeprefix(indent))
            i += 1
        if out and out[-1].strip():
            out.append("")
        out += [f"{indent}```pycon", *(indent + b for b in block), f"{indent}```"]
    return "\n".join(out)


class SphinxMarkup(griffe.Extension):
    """Rewrites every docstring of the loaded package (see the module's docstring)."""

    def on_package(self, *, pkg: griffe.Module, **kwargs) -> None:
        def visit(obj: griffe.Object) -> None:
            if obj.docstring is not None:
                obj.docstring.value = _doctest_blocks(_roles(obj.docstring.value, obj, pkg))
            for member in obj.members.values():
                if not member.is_alias:
                    visit(member)

        visit(pkg)
