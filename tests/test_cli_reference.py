"""docs/reference/cli.md is what scripts/cli_reference.py writes from the commands now."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import click

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "scripts" / "cli_reference.py"
PAGE = ROOT / "docs" / "reference" / "cli.md"


def _script():
    spec = importlib.util.spec_from_file_location("cli_reference", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_cli_reference_page_is_what_the_script_writes_from_the_commands():
    expected = _script().current_reference()
    written = PAGE.read_text(encoding="utf-8")
    assert written == expected, (
        "docs/reference/cli.md is stale: run `.venv/bin/python scripts/cli_reference.py` "
        "and commit the page"
    )


def test_cli_reference_names_every_command_of_the_lazy_group():
    from ajtwin.cli import main

    page = PAGE.read_text(encoding="utf-8")
    ctx = click.Context(main, info_name="ajtwin")
    for name in main.list_commands(ctx):
        command = main.get_command(ctx, name)
        assert f"`ajtwin {name}`" in page, name
        if isinstance(command, click.Group):
            sub_ctx = click.Context(command, info_name=name, parent=ctx)
            for sub in command.list_commands(sub_ctx):
                assert f"`ajtwin {name} {sub}`" in page, f"{name} {sub}"


def test_cli_reference_renders_usage_help_options_and_subcommands():
    @click.group()
    def tool():
        """A tool.

        Second paragraph | with a pipe."""

    @tool.command()
    @click.argument("record")
    @click.option("--rate", type=float, default=2.5, show_default=True, help="Rate, mL/s.")
    @click.option("--fast/--slow", default=False, help="Speed.")
    def run(record, rate, fast):
        """Run RECORD. Details follow."""

    page = _script().render_reference(tool, name="tool")
    body = page.split("\n## ", 1)[1]
    assert body == (
        "`tool`\n\n"
        "```text\ntool [OPTIONS] COMMAND [ARGS]...\n```\n\n"
        "A tool.\n\nSecond paragraph | with a pipe.\n\n"
        "| command | what it does |\n|---|---|\n"
        "| [`run`](#tool-run) | Run RECORD. Details follow. |\n\n"
        "### `tool run`\n\n"
        "```text\ntool run [OPTIONS] RECORD\n```\n\n"
        "Run RECORD. Details follow.\n\n"
        "| option | description |\n|---|---|\n"
        "| `--rate FLOAT` | Rate, mL/s. [default: 2.5] |\n"
        "| `--fast / --slow` | Speed. |\n"
    )


def _every_help(command, ctx):
    """(command path, its --help text) of a command and all its subcommands."""
    out = [(ctx.command_path, command.get_help(ctx))]
    if isinstance(command, click.Group):
        for name in command.list_commands(ctx):
            sub = command.get_command(ctx, name)
            out += _every_help(sub, click.Context(sub, info_name=name, parent=ctx))
    return out


def test_no_help_text_points_to_a_working_note_the_user_does_not_have():
    from ajtwin.cli import main

    outside = ".." + "/shared"  # the working note's folder, not named literally in the repo
    helps = _every_help(main, click.Context(main, info_name="ajtwin"))
    assert len(helps) > 30
    for path, text in helps:
        flat = " ".join(text.split())
        assert "SPEC" not in flat and outside not in flat, path
        # a section of the model is named by the file a user has
        assert "model reference §" not in flat, path
