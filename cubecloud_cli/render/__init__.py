"""One renderer for every image model of docs/design.md §3, on any scalar field over the world cube."""

from cubecloud_cli.render.image_models import IMAGE_MODELS, ImageModel, TransferFunction
from cubecloud_cli.render.renderer import render_view, render_views
from cubecloud_cli.render.samplers import FunctionField, GridField, Support, support_of_volume

__all__ = [
    "IMAGE_MODELS",
    "FunctionField",
    "GridField",
    "ImageModel",
    "Support",
    "TransferFunction",
    "render_view",
    "render_views",
    "support_of_volume",
]
