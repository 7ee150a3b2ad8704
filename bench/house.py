"""The house in order, measured: lines of cli/, the longest functions, how many places each
option's default is written, and the README's length.

    python bench/house.py
"""

from __future__ import annotations

import ast
import inspect
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import typer  # noqa: E402

from cubecloud_cli.cli import app  # noqa: E402
from cubecloud_cli.core.runtime import Runtime  # noqa: E402
from cubecloud_cli.cunerf import CunerfSettings  # noqa: E402
from cubecloud_cli.eval import EvalSettings  # noqa: E402
from cubecloud_cli.export import ExportSettings  # noqa: E402
from cubecloud_cli.preprocess import PreprocessSettings  # noqa: E402
from cubecloud_cli.presets import is_preset_key  # noqa: E402
from cubecloud_cli.splat.settings import SplatSettings  # noqa: E402

SETTINGS = (PreprocessSettings, CunerfSettings, ExportSettings, SplatSettings, EvalSettings, Runtime)


def longest_functions(package: Path, count: int = 5) -> list[tuple[int, str]]:
    found = []
    for path in package.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                found.append((node.end_lineno - node.lineno + 1, f"{path.relative_to(ROOT)}:{node.name}"))
    return sorted(found, reverse=True)[:count]


def literal_field_defaults(settings_class: type) -> dict[str, bool]:
    """For each field: whether its default is written as a literal in the class (not taken from presets.py)."""
    tree = ast.parse(inspect.getsource(settings_class).replace("\n    ", "\n", 0))
    body = tree.body[0].body  # type: ignore[attr-defined]
    return {
        node.target.id: not (
            isinstance(node.value, ast.Call) and getattr(node.value.func, "id", "") == "preset_default"
        )
        for node in body
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and node.value is not None
    }


def default_places() -> dict[str, int]:
    """Places each settings field's default value is written: presets.py (for a preset key), a literal in
    its settings class, and every command signature giving its option a default other than None."""
    places: dict[str, int] = {}
    signature_defaults: dict[str, int] = {}
    for command in typer.main.get_command(app).commands.values():  # type: ignore[attr-defined]
        for param in command.params:
            if type(param).__name__ == "TyperOption" and param.default not in (None, False) and param.name:
                signature_defaults[param.name] = signature_defaults.get(param.name, 0) + 1
    for settings_class in SETTINGS:
        stage = getattr(settings_class, "STAGE", None)
        for name, literal in literal_field_defaults(settings_class).items():
            key = f"{settings_class.__name__}.{name}"
            in_presets = bool(stage) and is_preset_key(stage, name)
            places[key] = int(in_presets) + int(literal) + signature_defaults.get(name, 0)
    return places


def main() -> None:
    cli_lines = sum(len(path.read_text().splitlines()) for path in (ROOT / "cubecloud_cli" / "cli").glob("*.py"))
    print(f"cli/: {cli_lines} lines in {len(list((ROOT / 'cubecloud_cli' / 'cli').glob('*.py')))} files")
    print("longest functions:")
    for lines, name in longest_functions(ROOT / "cubecloud_cli"):
        print(f"  {lines:4d}  {name}")
    places = default_places()
    worst = max(places.values())
    print(
        f"option defaults: {len(places)} settings fields, written in at most {worst} place(s); "
        f"fields written more than once: {[k for k, v in places.items() if v > 1] or 'none'}"
    )
    print(f"README.md: {len((ROOT / 'README.md').read_text().splitlines())} lines")


if __name__ == "__main__":
    main()
