"""`cubecloud run`'s orchestration: the five stages in order (``table``), the loop that skips,
resumes or runs each (``runner``), the two splat runs side by side (``side_by_side``) and the
rasterizer's kernels compiled ahead of them (``kernels_ahead``)."""
