"""Time `cubecloud preprocess` and measure its peak memory.

Runs each configuration in a fresh Python process (so the peak RSS is that run's own, imports
included) on the 512×512×48 chest CT from ../shared/data, or on a synthetic int16 scan of the
same shape and spacing when that folder is absent. Prints one row per configuration.

    python bench/preprocess.py                 # 256³ and 512³, pad, linear
    python bench/preprocess.py --sizes 128 256 --repeat 3
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CHEST = REPO.parent / "shared" / "data" / "ct_chest_5mm_pyradiomics_lung1.nii.gz"

CHILD = r"""
import json, resource, sys, time
start = time.perf_counter()
from cubecloud_cli.preprocess import PreprocessSettings, preprocess_scan
imported = time.perf_counter()
scan, work, size, fit, interpolation = sys.argv[1:6]
manifest = preprocess_scan(scan, work, PreprocessSettings(size=int(size), fit=fit, interpolation=interpolation, window="lung"))
end = time.perf_counter()
print(json.dumps({
    "import_s": imported - start,
    "stage_s": manifest["timings_s"]["total"],
    "phases": manifest["timings_s"],
    "process_s": end - start,
    "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
}))
"""


def synthetic_chest(path: Path) -> Path:
    import nibabel as nib
    import numpy as np

    rng = np.random.default_rng(0)
    data = rng.integers(-1024, 1500, size=(512, 512, 48), dtype=np.int16)
    nib.save(nib.Nifti1Image(data, np.diag([-0.5703, -0.5703, 5.0, 1.0])), str(path))
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--fit", default="pad")
    parser.add_argument("--interpolation", default="linear")
    parser.add_argument("--repeat", type=int, default=2, help="runs per size; the best is reported")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        scan = CHEST if CHEST.exists() else synthetic_chest(Path(tmp) / "synthetic_chest.nii.gz")
        print(f"scan: {scan.name} (512×512×48 int16, 0.57×0.57×5 mm)")
        print(f"{'size':>5} {'stage s':>8} {'process s':>10} {'peak MB':>8}  phases (s)")
        for size in args.sizes:
            runs = []
            for repeat in range(args.repeat):
                work = Path(tmp) / f"w{size}-{repeat}"
                output = subprocess.run(
                    [sys.executable, "-c", CHILD, str(scan), str(work), str(size), args.fit, args.interpolation],
                    capture_output=True,
                    text=True,
                    check=True,
                    cwd=REPO,
                )
                runs.append(json.loads(output.stdout.strip().splitlines()[-1]))
                subprocess.run(["rm", "-rf", str(work)], check=True)
            best = min(runs, key=lambda r: r["stage_s"])
            phases = " ".join(f"{k}={v:.2f}" for k, v in best["phases"].items() if k != "total")
            print(
                f"{size:>5} {best['stage_s']:>8.2f} {best['process_s']:>10.2f} {max(r['peak_rss_mb'] for r in runs):>8.0f}  {phases}"
            )


if __name__ == "__main__":
    main()
