"""The option tables of docs/commands.md, made from the commands themselves, so the reference
cannot drift from `--help` (tests/test_cli_options.py checks that it is current).

    python -m cubecloud_cli.cli.reference docs/commands.md     # rewrite the tables in place
"""

from __future__ import annotations

import re
import sys
import typing
from pathlib import Path

import typer

from cubecloud_cli.cli import app

BEGIN, END = "<!-- options: {} -->", "<!-- /options -->"


def command_function(command: str):
    """The function behind a command, as registered with the app."""
    return next(info.callback for info in app.registered_commands if info.name == command)


def option_annotation(command: str, param_name: str) -> object:
    """An option's type as its command function declares it, without typer's Annotated extras.
    Read from the function rather than from typer's parameter objects, whose internals differ
    between typer releases (the attribute that holds it has changed)."""
    return typing.get_type_hints(command_function(command))[param_name]


def _choices(command: str, param) -> str:
    annotation = option_annotation(command, param.name)
    for candidate in (annotation, *typing.get_args(annotation)):
        if typing.get_origin(candidate) is typing.Literal:
            return " " + "\\|".join(str(choice) for choice in typing.get_args(candidate))
    return ""


def options_table(command: str) -> str:
    """A markdown table of one command's arguments and options, with their --help text."""
    rows = ["| option | meaning |", "|---|---|"]
    for param in typer.main.get_command(app).commands[command].params:  # type: ignore[attr-defined]
        if type(param).__name__ == "TyperArgument":
            flags = (param.name or "").upper()
        else:
            flags = ", ".join(param.opts + param.secondary_opts) + _choices(command, param)
        meaning = (param.help or "").replace("|", "\\|")
        if getattr(param, "default", None) not in (None, False) and "(default" not in meaning:
            meaning += f" (default: {param.default})"
        rows.append(f"| `{flags}` | {meaning} |")
    return "\n".join(rows)


def rewrite(text: str) -> str:
    """``text`` with every marked table replaced by the command's current one."""

    def table(match: re.Match) -> str:
        return f"{BEGIN.format(match.group(1))}\n{options_table(match.group(1))}\n{END}"

    return re.sub(r"<!-- options: (\S+) -->.*?<!-- /options -->", table, text, flags=re.S)


if __name__ == "__main__":
    path = Path(sys.argv[1])
    path.write_text(rewrite(path.read_text()))
