"""Numerics every stage computes with: the numba settings of every parallel kernel (``jit``), Adam
without torch.optim (``adam``) and the image and volume metrics of docs/design.md §5 (``metrics``)."""
