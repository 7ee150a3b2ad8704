"""The cunerf stage: a cube-based neural field of the preprocessed volume (docs/cunerf.md)."""

from cubecloud_cli.core.lazy import lazy_exports
from cubecloud_cli.core.runtime import Runtime

_EXPORTS = {
    "CunerfField": "api",
    "CunerfSettings": "settings",
    "train_cunerf": "stage",
}
__getattr__ = lazy_exports(__name__, _EXPORTS)

__all__ = ["CunerfField", "CunerfSettings", "Runtime", "train_cunerf"]
