"""One renderer for every image model of docs/design.md §3, on any scalar field over the world cube."""

from cubecloud_cli.core.lazy import lazy_exports

_EXPORTS = {
    "IMAGE_MODELS": "image_model_names",
    "ImageModel": "image_models",
    "render_view": "renderer",
    "render_views": "renderer",
    "FunctionField": "samplers",
    "GridField": "samplers",
    "Support": "samplers",
    "support_of_volume": "samplers",
}
__getattr__ = lazy_exports(__name__, _EXPORTS)

__all__ = [
    "FunctionField",
    "GridField",
    "IMAGE_MODELS",
    "ImageModel",
    "Support",
    "render_view",
    "render_views",
    "support_of_volume",
]
