"""The command line reads its options without the stages: `--help` and `--version` import no
torch, numba or scipy, which took seconds per process (cubecloud_cli/core/lazy.py)."""

from __future__ import annotations

import importlib
import subprocess
import sys
import types

import pytest

from cubecloud_cli.core.lazy import lazy_exports

COMMANDS = ("preprocess", "cunerf", "export", "splat", "eval", "run", "view", "cohort")
HEAVY = ("torch", "numba", "scipy", "nibabel", "skimage", "viser", "snakemake")
LAZY_PACKAGES = ("cunerf", "eval", "export", "preprocess", "render", "splat")


def test_help_and_version_import_no_stage():
    probe = (
        "import sys\n"
        "from typer.testing import CliRunner\n"
        "from cubecloud_cli.cli import app\n"
        f"for args in [['--version'], ['--help'], *[[c, '--help'] for c in {COMMANDS!r}]]:\n"
        "    result = CliRunner().invoke(app, args)\n"
        "    assert result.exit_code == 0, (args, result.output)\n"
        f"print(' '.join(m for m in {HEAVY!r} if m in sys.modules) or 'none')\n"
    )
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["none"]


@pytest.mark.parametrize("package", LAZY_PACKAGES)
def test_every_public_name_of_a_stage_package_resolves(package):
    module = importlib.import_module(f"cubecloud_cli.{package}")
    for name in module.__all__:
        assert getattr(module, name) is not None, name
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        module.not_a_name  # noqa: B018


def test_a_lazy_name_is_imported_once_then_read_as_a_plain_attribute(monkeypatch):
    package = types.ModuleType("fake_package")
    monkeypatch.setitem(sys.modules, "fake_package", package)
    submodule = types.ModuleType("fake_package.part")
    submodule.value = object()
    monkeypatch.setitem(sys.modules, "fake_package.part", submodule)
    package.__getattr__ = lazy_exports("fake_package", {"value": "part"})
    assert "value" not in vars(package)
    assert package.value is submodule.value
    assert vars(package)["value"] is submodule.value  # later reads skip __getattr__
