"""The small real CT that ships with the package, so every command works out of the box."""

from importlib import resources
from pathlib import Path

SAMPLE_CT_NAME = "ct_abdomen_pelvis_3mm_totalseg.nii.gz"
SAMPLE_CT_ATTRIBUTION = (
    "bundled abdomen/pelvis CT from TotalSegmentator (Apache-2.0; Wasserthal et al., Radiology: AI 2023)"
)


def sample_ct_path() -> Path:
    """Path of the bundled abdomen CT (122×101×112 voxels, 3 mm, HU)."""
    return Path(str(resources.files("cubecloud_cli") / "data" / SAMPLE_CT_NAME))
