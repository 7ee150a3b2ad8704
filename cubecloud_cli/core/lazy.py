"""Package attributes imported at first use (PEP 562).

A stage package's public names (``from cubecloud_cli.cunerf import train_cunerf``) live in
modules that import torch, numba or scipy: seconds of imports. The command line needs only the
settings classes to build its options, so `cubecloud --help` and `--version` should not pay for
the stages (a command that runs imports its stage first, and then checks its inputs). Each package maps its public names to the
modules that define them, and a name's module is imported when the name is first read.
"""

from __future__ import annotations

import importlib
import sys
from typing import Any, Callable, Mapping


def lazy_exports(package: str, exports: Mapping[str, str]) -> Callable[[str], Any]:
    """The ``__getattr__`` of ``package``: ``exports`` maps each public name to the module (a
    submodule's name, relative to ``package``) that defines it."""

    def __getattr__(name: str) -> Any:
        submodule = exports.get(name)
        if submodule is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{submodule}"), name)
        setattr(sys.modules[package], name, value)  # read once; later reads skip this function
        return value

    return __getattr__
