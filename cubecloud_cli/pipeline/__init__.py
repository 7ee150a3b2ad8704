"""`cubecloud run`'s orchestration: the five stages in order (``table``), the loop that skips,
resumes or runs each (``runner``), stages run side by side (``side_by_side``) and what a stage will
compile compiled ahead (``kernels_ahead``)."""

from cubecloud_cli.core.lazy import lazy_exports

_EXPORTS = {
    "run_pipeline": "table",
    "run_stages": "runner",
    "stage_table": "table",
}
__getattr__ = lazy_exports(__name__, _EXPORTS)

__all__ = ["run_pipeline", "run_stages", "stage_table"]
