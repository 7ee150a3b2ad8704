"""The package's house rules (docs/design.md §7), read from the code's own imports: every import
is one the layer table allows, no import runs up the table, no modules import each other in a
circle, the root holds few loose modules, and no file name means two things."""

from __future__ import annotations

import ast
import re
from collections import Counter
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
PACKAGE = REPO / "cubecloud_cli"
DESIGN = REPO / "docs" / "design.md"
EVERYTHING_BELOW = "everything below"
# Names every stage has one of, meaning the same thing in each.
SHARED_FILE_NAMES = {"__init__.py", "stage.py", "settings.py"}
MAX_LOOSE_MODULES = 6


def layer_table(text: str) -> list[tuple[str, set[str] | str]]:
    """The rows of §7's table, top to bottom: (folder or module, the units it may import, or
    EVERYTHING_BELOW). A unit is written ``name/`` for a folder and ``name.py`` for a module."""
    section = text[text.index("## 7. Where the code lives") :]
    rows = []
    for line in section.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) != 3 or not cells[0].startswith("`"):
            continue
        unit = cells[0].strip("`")
        allowed = cells[2]
        if allowed == EVERYTHING_BELOW:
            rows.append((unit, EVERYTHING_BELOW))
        else:
            rows.append((unit, set(re.findall(r"`([^`]+)`", allowed))))
    return rows


def unit_of(module: str) -> str | None:
    """``cubecloud_cli.splat.trainer`` -> ``splat/``; ``cubecloud_cli.presets`` -> ``presets.py``;
    None for the package itself (its version, importable from anywhere)."""
    parts = module.split(".")
    if parts[0] != "cubecloud_cli":
        return None
    if len(parts) == 1:
        return None
    return f"{parts[1]}/" if (PACKAGE / parts[1]).is_dir() else f"{parts[1]}.py"


def module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def is_module(name: str) -> bool:
    relative = Path(*name.split("."))
    return (REPO / relative).with_suffix(".py").is_file() or (REPO / relative / "__init__.py").is_file()


def imports_of(path: Path) -> set[str]:
    """Every cubecloud module that ``path`` imports, anywhere in it (functions and TYPE_CHECKING
    blocks too): ``from a.b import c`` is a.b.c where that is a module, else a.b."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                full = f"{node.module}.{alias.name}"
                found.add(full if is_module(full) else node.module)
    return {name for name in found if name.split(".")[0] == "cubecloud_cli"}


def package_modules() -> dict[str, Path]:
    return {module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


def import_graph() -> dict[str, set[str]]:
    modules = package_modules()
    return {name: {m for m in imports_of(path) if m in modules and m != name} for name, path in modules.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for successor in graph.get(node, ()):
            if successor not in index:
                visit(successor)
                low[node] = min(low[node], low[successor])
            elif successor in on_stack:
                low[node] = min(low[node], index[successor])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def unit_edges(graph: dict[str, set[str]]) -> set[tuple[str, str, str, str]]:
    """(importing unit, imported unit, importing module, imported module) across units."""
    edges = set()
    for source, targets in graph.items():
        for target in targets:
            a, b = unit_of(source), unit_of(target)
            if a is not None and b is not None and a != b:
                edges.add((a, b, source, target))
    return edges


def allowed_by_table(rows) -> dict[str, set[str]]:
    names = [unit for unit, _ in rows]
    return {
        unit: set(names[position + 1 :]) if allowed == EVERYTHING_BELOW else allowed
        for position, (unit, allowed) in enumerate(rows)
    }


@pytest.fixture(scope="module")
def rows():
    return layer_table(DESIGN.read_text())


def test_the_table_names_every_folder_and_loose_module_once(rows):
    names = [unit for unit, _ in rows]
    assert len(names) == len(set(names))
    present = {f"{p.name}/" for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()}
    present |= {p.name for p in PACKAGE.glob("*.py") if p.name != "__init__.py"}
    assert set(names) == present


def test_each_row_may_import_only_rows_below_it(rows):
    names = [unit for unit, _ in rows]
    for position, (unit, allowed) in enumerate(rows):
        if allowed == EVERYTHING_BELOW:
            continue
        unknown = allowed - set(names)
        assert not unknown, f"{unit} may import {unknown}, which the table does not list"
        above = allowed & set(names[: position + 1])
        assert not above, f"{unit} may import {above}, at or above its own row"


def test_every_import_is_one_the_table_allows(rows):
    allowed = allowed_by_table(rows)
    refused = sorted(
        f"{source} imports {target} ({a} may not import {b})"
        for a, b, source, target in unit_edges(import_graph())
        if b not in allowed[a]
    )
    assert not refused, "\n".join(refused)


def test_no_modules_import_each_other_in_a_circle():
    assert cycles(import_graph()) == []


def test_the_root_holds_few_loose_modules():
    loose = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert len(loose) <= MAX_LOOSE_MODULES, loose


def test_no_file_name_is_used_for_two_things():
    names = Counter(p.name for p in PACKAGE.rglob("*.py"))
    assert {name for name, count in names.items() if count > 1} <= SHARED_FILE_NAMES


# The checks themselves, on small made-up graphs and tables: each must catch what it is for.


def test_the_cycle_finder_finds_a_circle_and_nothing_else():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []


def test_an_import_up_the_table_is_refused():
    rows = layer_table(
        "## 7. Where the code lives\n| folder | for | may import |\n|---|---|---|\n"
        "| `cli/` | x | everything below |\n| `splat/` | x | `core/` |\n| `core/` | x | `splat/` |\n"
    )
    assert rows == [("cli/", EVERYTHING_BELOW), ("splat/", {"core/"}), ("core/", {"splat/"})]
    allowed = allowed_by_table(rows)
    assert allowed["cli/"] == {"splat/", "core/"}
    with pytest.raises(AssertionError, match="at or above"):
        test_each_row_may_import_only_rows_below_it(rows)


def test_imports_inside_functions_count(tmp_path):
    source = tmp_path / "module.py"
    source.write_text(
        "def f():\n    from cubecloud_cli.core.errors import CubecloudError\n    import cubecloud_cli.cli\n"
    )
    assert imports_of(source) == {"cubecloud_cli.core.errors", "cubecloud_cli.cli"}


def test_validate_means_one_thing_with_one_signature():
    """Every ``validate`` checks its own options and takes nothing else (what depends on the data
    has a name of its own, such as ``check_for_volume``)."""
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef) and node.name == "validate":
                arguments = [a.arg for a in node.args.posonlyargs + node.args.args + node.args.kwonlyargs]
                assert arguments == ["self"], f"{path}:{node.lineno} validate{tuple(arguments)}"
                assert ast.unparse(node.returns) == "None", f"{path}:{node.lineno} validate returns a value"
