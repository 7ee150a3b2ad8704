"""DICOM reading: agreement with dcm2niix and with the ground truth on synthetic series, and the
read time of a long series.

    python bench/dicom.py                 # every synthetic case, then a 500-slice 512² series
    python bench/dicom.py --slices 200    # a shorter long series
    python bench/dicom.py --no-timing     # the agreement table only

The series are written with pydicom from the phantom of tests/dicom_phantoms.py, defined in
scanner space, so every pixel holds the phantom at its own position. For each case it prints
Pearson r between our volume and dcm2niix's (its corrected _Tilt/_Eq file when it writes one) on
our body voxels, sampled at the same scanner positions through each file's affine (nearest
voxel), and each volume's r against the phantom itself at its own voxel centres.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from dicom_phantoms import (  # noqa: E402
    LPS_TO_RAS,
    correlation_with_nifti,
    correlation_with_phantom,
    dcm2niix_volume,
    phantom_hu,
    write_enhanced,
    write_series,
)

from cubecloud_cli.volume.readers import read_scan  # noqa: E402

EVEN = list(np.arange(0.0, 62.6, 2.5))
MISSING = [z for z in EVEN if z != 30.0]
CASES = {
    "even": lambda d: write_series(d, EVEN),
    "a missing slice": lambda d: write_series(d, MISSING),
    "thin (1 mm) and thick (7 mm) slabs": lambda d: write_series(
        d, [*np.arange(0.0, 24.0, 1.0), *np.arange(24.0, 63.0, 7.0)]
    ),
    "overlapping slabs": lambda d: write_series(d, [*np.arange(0.0, 40.0, 2.5), *np.arange(33.75, 62.0, 2.5)]),
    "gantry tilt +20° (dcm2niix's sign)": lambda d: write_series(d, EVEN, tilt_deg=-20.0),
    "gantry tilt −20° (dcm2niix's sign)": lambda d: write_series(d, EVEN, tilt_deg=20.0),
    "tilt +20° and a missing slice": lambda d: write_series(d, MISSING, tilt_deg=-20.0),
    "enhanced multi-frame, a missing frame": lambda d: (
        write_enhanced(d / "ct.dcm", MISSING, varying_rescale=False).parent
    ),
    "enhanced, per-frame rescale": lambda d: write_enhanced(d / "ct.dcm", MISSING).parent,
    "enhanced, tilt +20°": lambda d: write_enhanced(d / "ct.dcm", EVEN, tilt_deg=-20.0, varying_rescale=False).parent,
}


def nifti_vs_phantom(path: Path) -> float:
    import nibabel as nib

    image = nib.load(str(path))
    data = np.asarray(image.dataobj, dtype=np.float32).reshape(image.shape[:3])
    index = np.stack(np.meshgrid(*[np.arange(n) for n in data.shape], indexing="ij"), -1).reshape(-1, 3)
    lps = (LPS_TO_RAS @ image.affine @ np.c_[index, np.ones(len(index))].T)[:3].T
    return float(np.corrcoef(data.reshape(-1), phantom_hu(lps))[0, 1])


def agreement_table(scratch: Path) -> None:
    print("| case | r, ours vs dcm2niix (body) | r, ours vs truth | r, dcm2niix vs truth | dcm2niix file |")
    print("|---|---|---|---|---|")
    for number, (case, write) in enumerate(CASES.items()):
        source = write(scratch / f"case{number}" / "dicom")
        ours = read_scan(source)
        theirs = dcm2niix_volume(source, scratch / f"case{number}" / "nifti")
        print(f"| {case} | {correlation_with_nifti(ours, theirs):.4f} | {correlation_with_phantom(ours):.4f} "
              f"| {nifti_vs_phantom(theirs):.4f} | {theirs.name} |")  # fmt: skip


def read_time(scratch: Path, slices: int, tilt_deg: float) -> None:
    folder = scratch / f"long{tilt_deg:+.0f}"
    started = time.perf_counter()
    write_series(folder, list(np.arange(slices) * 1.0 - slices / 4), tilt_deg=tilt_deg, rows=512, columns=512,
                 spacing=(0.7, 0.7))  # fmt: skip
    written = time.perf_counter() - started
    started = time.perf_counter()
    scan = read_scan(folder)
    seconds = time.perf_counter() - started
    size_mb = sum(p.stat().st_size for p in folder.iterdir()) / 1e6
    print(f"{slices} slices of 512², tilt {tilt_deg:g}°: read in {seconds:.1f} s ({slices / seconds:.0f} slices/s, "
          f"{size_mb:.0f} MB), volume {scan.data.shape}; written in {written:.0f} s")  # fmt: skip
    shutil.rmtree(folder)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--slices", type=int, default=500)
    parser.add_argument("--no-timing", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        if shutil.which("dcm2niix"):
            agreement_table(Path(scratch))
        else:
            print("dcm2niix not found (pip install dcm2niix): agreement table skipped")
        if not args.no_timing:
            for tilt in (0.0, 20.0):
                read_time(Path(scratch), args.slices, tilt)


if __name__ == "__main__":
    main()
