"""The export stage: CuNeRF's cube point cloud, orbit cameras and rendered views as a COLMAP scene."""

from cubecloud_cli.core.lazy import lazy_exports

_EXPORTS = {
    "ExportSettings": "settings",
    "export_scene": "stage",
}
__getattr__ = lazy_exports(__name__, _EXPORTS)

__all__ = ["ExportSettings", "export_scene"]
