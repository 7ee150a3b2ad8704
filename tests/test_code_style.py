"""The formatter and import order pyproject.toml sets, applied to the whole repository."""

import shutil
import subprocess

import pytest
from conftest import REPO

RUFF = shutil.which("ruff")


@pytest.mark.skipif(RUFF is None, reason="ruff is in the test extras: pip install -e '.[test]'")
@pytest.mark.parametrize("command", [["format", "--check"], ["check"]])
def test_the_code_is_formatted_and_its_imports_are_in_order(command):
    result = subprocess.run([RUFF, *command, str(REPO)], capture_output=True, text=True, cwd=REPO)
    assert result.returncode == 0, result.stdout + result.stderr
