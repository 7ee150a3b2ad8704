"""`cubecloud eval`: held-out scores of every splat run and of CuNeRF against the reference renders
of the volume (docs/design.md §5), pictures, and tables across work directories."""

from cubecloud_cli.core.lazy import lazy_exports

_EXPORTS = {
    "EvalSettings": "settings",
    "evaluate_work": "stage",
    "score_view": "scoring",
    "score_views": "scoring",
    "summarize": "scoring",
}
__getattr__ = lazy_exports(__name__, _EXPORTS)

__all__ = ["EvalSettings", "evaluate_work", "score_view", "score_views", "summarize"]
