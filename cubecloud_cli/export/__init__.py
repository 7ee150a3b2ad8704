"""The export stage: CuNeRF's cube point cloud, orbit cameras and rendered views as a COLMAP scene."""

from cubecloud_cli.export.settings import ExportSettings
from cubecloud_cli.export.stage import export_scene

__all__ = ["ExportSettings", "export_scene"]
