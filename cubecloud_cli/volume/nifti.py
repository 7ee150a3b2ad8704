"""Write a float32 volume as NIfTI-1 in slabs, so long writes can report progress."""

from __future__ import annotations

import gzip
from pathlib import Path
from typing import Callable

import numpy as np

_HEADER_BYTES = 348
_DATA_OFFSET = 352  # header + the 4-byte "no extensions" flag


def write_nifti(
    volume: np.ndarray,
    affine: np.ndarray,
    path: Path,
    description: str = "",
    on_progress: Callable[[float], None] = lambda fraction: None,
    slab_bytes: int = 32 << 20,
) -> None:
    """Write ``volume`` (float32, RAS-ordered x, y, z) to ``path`` (.nii or .nii.gz).

    The affine goes into both the sform and the qform with code 1 (scanner), so every viewer
    places the volume the same way. ``on_progress`` gets the fraction written so far.
    """
    import nibabel as nib

    volume = np.asarray(volume, dtype=np.float32)
    image = nib.Nifti1Image(np.empty((1, 1, 1), np.float32), affine)
    header = image.header
    header.set_data_shape(volume.shape)
    header.set_data_dtype(np.float32)
    image.set_qform(affine, code=1)
    image.set_sform(affine, code=1)
    header.set_xyzt_units("mm")
    header["descrip"] = description[:79].encode()
    header["cal_min"], header["cal_max"] = float(volume.min()), float(volume.max())
    header["vox_offset"] = _DATA_OFFSET
    header["scl_slope"], header["scl_inter"] = 1.0, 0.0

    opener = gzip.open(path, "wb", compresslevel=1) if str(path).endswith(".gz") else open(path, "wb")
    depth = volume.shape[2]
    plane_bytes = volume.shape[0] * volume.shape[1] * 4
    step = max(1, slab_bytes // plane_bytes)
    with opener as handle:
        handle.write(header.binaryblock[:_HEADER_BYTES])
        handle.write(b"\0" * (_DATA_OFFSET - _HEADER_BYTES))
        # NIfTI stores x fastest: whole z-planes are contiguous runs of the file.
        for start in range(0, depth, step):
            handle.write(volume[:, :, start : start + step].tobytes(order="F"))
            on_progress(min(1.0, (start + step) / depth))
