"""`cubecloud run`'s orchestration: the stages in order (``runner``), the two splat runs side by side
(``side_by_side``) and the rasterizer's kernels compiled ahead of them (``kernels_ahead``)."""
