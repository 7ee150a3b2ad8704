"""The cunerf stage: a cube-based neural field of the preprocessed volume (docs/cunerf.md)."""

from cubecloud_cli.cunerf.api import CunerfField
from cubecloud_cli.cunerf.settings import CunerfSettings
from cubecloud_cli.cunerf.stage import train_cunerf
from cubecloud_cli.runtime import Runtime

__all__ = ["CunerfField", "CunerfSettings", "Runtime", "train_cunerf"]
