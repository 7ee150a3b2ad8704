"""The scans of a cohort, each with an id that names its work directory OUT/<id>/.

From arguments: a scan file, a DICOM series folder, or a folder of them (each NIfTI file and
each DICOM series folder in it). From a CSV (``--scans cohort.csv``): columns id and scan, and
optionally window and modality per scan.
"""

from __future__ import annotations

import csv
import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.volume.intensity import MODALITIES, WINDOW_NAMES
from cubecloud_cli.volume.readers import is_dicom_file

NIFTI_SUFFIXES = (".nii.gz", ".nii")
ID_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
CHOICES = {"window": WINDOW_NAMES, "modality": MODALITIES}  # the optional columns, as preprocess takes them


@dataclass(frozen=True)
class CohortScan:
    id: str
    scan: Path
    window: str | None = None
    modality: str | None = None


def scan_id(path: Path) -> str:
    """A folder-safe id from a scan's name: its stem without .nii(.gz), other characters as _."""
    name = path.name
    for suffix in NIFTI_SUFFIXES:
        if name.lower().endswith(suffix):
            name = name[: -len(suffix)]
            break
    cleaned = re.sub(r"[^A-Za-z0-9._-]", "_", name).lstrip("._-")
    return cleaned or "scan"


def is_dicom_series(folder: Path) -> bool:
    return any(is_dicom_file(p) for p in sorted(folder.iterdir())[:50] if p.is_file())


def _scans_in(folder: Path) -> list[Path]:
    """A DICOM series folder is one scan; any other folder holds its NIfTI files and series folders."""
    if is_dicom_series(folder):
        return [folder]
    found = []
    for child in sorted(folder.iterdir()):
        if child.is_file() and child.name.lower().endswith(NIFTI_SUFFIXES):
            found.append(child)
        elif child.is_dir() and is_dicom_series(child):
            found.append(child)
    if not found:
        raise CubecloudError(f"{folder} holds no NIfTI file and no DICOM series folder: point at the scans themselves")
    return found


def scans_from_arguments(arguments: list[Path]) -> list[CohortScan]:
    scans = []
    for argument in arguments:
        path = Path(argument)
        if not path.exists():
            raise CubecloudError(f"{path} does not exist: check the path")
        for scan in _scans_in(path) if path.is_dir() else [path]:
            scans.append(CohortScan(scan_id(scan), scan.resolve()))
    return check_ids(scans, "give them ids in a --scans CSV (columns id,scan)")


def scans_from_csv(path: Path) -> list[CohortScan]:
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as file:  # a spreadsheet's byte-order mark is no column
            rows = list(csv.DictReader(file))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise CubecloudError(f"cannot read {path} ({exc}): it must be a CSV file with columns id,scan") from None
    if not rows or not {"id", "scan"} <= set(rows[0]):
        raise CubecloudError(f"{path} needs the columns id,scan (and optionally window, modality)")
    scans = []
    for number, row in enumerate(rows, start=2):
        scan = Path((row.get("scan") or "").strip())
        if not scan.is_absolute():
            scan = path.parent / scan  # relative to the CSV, wherever the command runs
        if not (row.get("scan") or "").strip() or not scan.exists():
            raise CubecloudError(f"{path} line {number}: scan {str(row.get('scan'))!r} does not exist")
        window, modality = (_choice(path, number, row, column, allowed) for column, allowed in CHOICES.items())
        scans.append(CohortScan((row.get("id") or "").strip(), scan.resolve(), window, modality))
    return check_ids(scans, f"make the ids in {path} unique")


def _choice(path: Path, line: int, row: dict, column: str, allowed: tuple[str, ...]) -> str | None:
    """The row's value in an optional column: None when empty, else one of ``allowed``."""
    value = (row.get(column) or "").strip()
    if value and value not in allowed:
        raise CubecloudError(f"{path} line {line}, column {column}: {value!r} must be one of {', '.join(allowed)}")
    return value or None


def check_ids(scans: list[CohortScan], fix: str) -> list[CohortScan]:
    if not scans:
        raise CubecloudError("no scans given: name scan files or folders, or a --scans CSV")
    bad = [scan.id for scan in scans if not ID_PATTERN.match(scan.id) or scan.id == "cohort"]
    if bad:
        raise CubecloudError(
            f"scan id {bad[0]!r} cannot name a folder: use letters, digits, '.', '_' and '-' (and not 'cohort')"
        )
    repeated = [name for name, count in Counter(scan.id for scan in scans).items() if count > 1]
    if repeated:
        raise CubecloudError(f"two scans have the id {repeated[0]!r}: {fix}")
    return scans
