"""`cubecloud eval`: held-out scores of every splat run and of CuNeRF against the reference renders
of the volume (docs/design.md §5), pictures, and tables across work directories."""

from cubecloud_cli.eval.scoring import score_view, score_views, summarize
from cubecloud_cli.eval.settings import EvalSettings
from cubecloud_cli.eval.stage import evaluate_work

__all__ = ["EvalSettings", "evaluate_work", "score_view", "score_views", "summarize"]
