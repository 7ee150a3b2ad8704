"""Use a trained CuNeRF field from Python: sample it anywhere, at any resolution.

    cubecloud run -o work                       # or: cubecloud preprocess ... && cubecloud cunerf ...
    python examples/cunerf_field.py work --scale 2 --out work/field_x2.nii.gz

Prints the field's intensity and density along the left-right line through the centre of the
volume, then writes the field baked at --scale × the volume's resolution as a NIfTI that lies
over the original scan (open it beside the scan in 3D Slicer or ITK-SNAP).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from cubecloud_cli.cunerf import CunerfField
from cubecloud_cli.volume.nifti import write_nifti


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("work", type=Path, help="work directory with a complete cunerf/ stage")
    parser.add_argument("--scale", type=float, default=2.0, help="bake resolution as a multiple of the volume's")
    parser.add_argument("--out", type=Path, default=None, help="NIfTI to write (default WORK/field_xSCALE.nii.gz)")
    parser.add_argument("--device", default="auto")
    args = parser.parse_args()

    field = CunerfField.load(args.work, device=args.device)
    print(f"field trained on a {field.volume_size}³ volume; cube half-size {field.cube_half_size:.4f} world units")

    # World coordinates: the volume fills [-1, 1]³, x left→right, y posterior→anterior, z inferior→superior.
    line = np.zeros((9, 3), dtype=np.float32)
    line[:, 0] = np.linspace(-0.8, 0.8, 9)
    intensity, density = field.query(line)
    print("x (world)   intensity   density")
    for x, value, sigma in zip(line[:, 0], intensity, density):
        print(f"{x:+9.2f}   {value:9.4f}   {sigma:7.3f}")

    size = round(field.volume_size * args.scale)
    volume = field.bake(size)
    out = args.out or args.work / f"field_x{args.scale:g}.nii.gz"
    write_nifti(volume, field.bake_affine(size), out, f"cubecloud field x{args.scale:g}")
    print(f"wrote {out}: {size}³, values {volume.min():.3f}..{volume.max():.3f}")


if __name__ == "__main__":
    main()
