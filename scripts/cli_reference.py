"""Write docs/reference/cli.md from the ``ajtwin`` command line itself.

Walks the lazy click group ``ajtwin.cli:main`` and every subgroup and writes, per
command, its usage line, its help text, its options (as ``--help`` prints them, with
defaults and ranges) and, for a group, its subcommands. The page is generated, never
edited by hand: change a command's help in the code, then run

    .venv/bin/python scripts/cli_reference.py           # writes docs/reference/cli.md
    .venv/bin/python scripts/cli_reference.py --check   # exit 1 if the page is stale

``tests/test_cli_reference.py`` fails when the committed page differs from what this
script writes now.

Example
-------
>>> from ajtwin.cli import main                          # doctest: +SKIP
>>> render_reference(main).startswith("# Command-line reference")   # doctest: +SKIP
True
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import click

ROOT = Path(__file__).resolve().parent.parent
OUTPUT = ROOT / "docs" / "reference" / "cli.md"

#: Help text is wrapped at this width for the usage lines; fixed so the page does
#: not depend on the terminal it was generated in.
WIDTH = 88

HEADER = """\
# Command-line reference

Every `ajtwin` command with its usage, help and options, as `ajtwin COMMAND --help`
prints them (every command also takes `--help`). This page is generated from the
commands by `scripts/cli_reference.py`; do not edit it by hand
(`tests/test_cli_reference.py` fails when it is stale). Units of every option are those
of the [model reference](model.md#3-states-inputs-outputs-and-units): µm, mL, mA, sccm,
Pa, s.

Every command that reads or writes the machine registry takes `--store PATH`
(default: `$AJTWIN_STORE`, else `$XDG_DATA_HOME/ajtwin/registry.sqlite`, else
`~/.local/share/ajtwin/registry.sqlite`); see the [registry reference](registry.md).
"""


def _context(command: click.Command, name: str, parent: click.Context | None) -> click.Context:
    return click.Context(
        command, info_name=name, parent=parent, terminal_width=WIDTH, max_content_width=WIDTH
    )


def _anchor(path: str) -> str:
    """GitHub-style anchor of a heading ``ajtwin machine add`` → ``ajtwin-machine-add``."""
    return re.sub(r"[^a-z0-9 -]", "", path.lower()).replace(" ", "-")


def _cell(text: str) -> str:
    """Text for one markdown table cell: one line, pipes escaped."""
    return " ".join(text.split()).replace("|", "\\|")


def _help_text(command: click.Command) -> str:
    """The command's help as markdown paragraphs (click's ``\\f`` cut honoured)."""
    text = (command.help or command.short_help or "").split("\f")[0]
    paragraphs = [" ".join(p.split()) for p in re.split(r"\n\s*\n", text.strip()) if p.strip()]
    return "\n\n".join(paragraphs)


def _walk(command: click.Command, ctx: click.Context):
    """Yield (context, command) for the command and, depth first, every subcommand."""
    yield ctx, command
    if isinstance(command, click.Group):
        for name in command.list_commands(ctx):
            sub = command.get_command(ctx, name)
            if sub is None or sub.hidden:
                continue
            yield from _walk(sub, _context(sub, name, ctx))


def _section(ctx: click.Context, command: click.Command) -> str:
    path = ctx.command_path
    depth = path.count(" ")
    lines = [f"{'#' * min(depth + 2, 4)} `{path}`", ""]
    usage = " ".join([path, *command.collect_usage_pieces(ctx)])
    lines += ["```text", usage, "```", ""]
    help_text = _help_text(command)
    if help_text:
        lines += [help_text, ""]
    rows = []
    help_option = command.get_help_option(ctx)
    for param in command.get_params(ctx):
        if param is help_option or isinstance(param, click.Argument):
            continue  # every command takes --help; arguments are named in the usage line
        record = param.get_help_record(ctx)
        if record is None:
            continue
        option, description = record
        rows.append(f"| `{_cell(option)}` | {_cell(description)} |")
    if rows:
        lines += ["| option | description |", "|---|---|", *rows, ""]
    if isinstance(command, click.Group):
        subs = []
        for name in command.list_commands(ctx):
            sub = command.get_command(ctx, name)
            if sub is None or sub.hidden:
                continue
            short = _cell(_help_text(sub).split("\n\n")[0])
            subs.append(f"| [`{name}`](#{_anchor(f'{path} {name}')}) | {short} |")
        if subs:
            lines += ["| command | what it does |", "|---|---|", *subs, ""]
    return "\n".join(lines)


def render_reference(main: click.Command, name: str = "ajtwin") -> str:
    """The whole reference page for the group ``main`` as markdown text."""
    sections = [_section(ctx, command) for ctx, command in _walk(main, _context(main, name, None))]
    return HEADER + "\n" + "\n".join(sections).rstrip() + "\n"


def current_reference() -> str:
    """The page for the installed ``ajtwin.cli:main``."""
    from ajtwin.cli import main

    return render_reference(main)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=OUTPUT, help="page to write")
    parser.add_argument("--check", action="store_true", help="exit 1 if the page is stale")
    args = parser.parse_args(argv)
    text = current_reference()
    if args.check:
        stale = not args.out.is_file() or args.out.read_text(encoding="utf-8") != text
        if stale:
            print(f"{args.out} is stale: run python scripts/cli_reference.py", file=sys.stderr)
        return 1 if stale else 0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text, encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
