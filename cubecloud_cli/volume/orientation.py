"""Reorientation to RAS+ (nibabel's canonical orientation) without resampling."""

from __future__ import annotations

import numpy as np
from nibabel.orientations import (
    aff2axcodes,
    apply_orientation,
    axcodes2ornt,
    inv_ornt_aff,
    io_orientation,
    ornt_transform,
)


def axis_codes(affine: np.ndarray) -> str:
    """'LPS', 'RAS', ...: where each array axis points (nibabel's aff2axcodes)."""
    return "".join(aff2axcodes(affine))


def reorient_to_ras(data: np.ndarray, affine: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flip and permute array axes so they run left→right, posterior→anterior, inferior→superior.

    Only axis flips and transpositions are applied, so voxel values are untouched and every
    voxel keeps its scanner position: ``new_affine @ new_index == affine @ old_index``. For an
    oblique scan the axes are the closest RAS ones and the residual rotation stays in the affine.
    Returns a view of ``data`` where possible.
    """
    transform = ornt_transform(io_orientation(affine), axcodes2ornt("RAS"))
    new_affine = affine @ inv_ornt_aff(transform, data.shape)
    return apply_orientation(data, transform), new_affine
