"""The preprocess stage: read, repair, reorient, window, resample, write.

WORK/preprocess/ holds
  volume.npy      float32 S×S×S in [0, 1], axes RAS (x left→right, y posterior→anterior,
                  z inferior→superior); np.load(..., mmap_mode="r") maps it without reading it
  volume.nii.gz   the same voxels with the affine that lays them over the original scan
  preview.png     axial, coronal and sagittal mid-slices
  manifest.json   parameters, input sha256, timings and the voxel ↔ world ↔ scanner maps
"""

from __future__ import annotations

import logging
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from cubecloud_cli.core.artifacts import StageWriter, check_free_disk, read_manifest
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.core.pictures import write_preview
from cubecloud_cli.core.progress import ProgressCallback, no_progress
from cubecloud_cli.core.runtime import Runtime
from cubecloud_cli.core.stage import Stage
from cubecloud_cli.core.writes import save_array
from cubecloud_cli.preprocess.settings import SIZE_FROM_SCAN, PreprocessSettings
from cubecloud_cli.volume.cube_frame import (
    MIN_VOXELS_ACROSS,
    SCAN_SIZE_CAP,
    CubeFrame,
    Fit,
    plan_cube,
    shear_degrees,
    size_for_scan,
    size_keeping,
    voxels_across,
)
from cubecloud_cli.volume.intensity import IntensityMap, detect_modality, replace_nonfinite, resolve_intensity_map
from cubecloud_cli.volume.nifti import write_nifti
from cubecloud_cli.volume.orientation import axis_codes, reorient_to_ras
from cubecloud_cli.volume.readers import read_scan
from cubecloud_cli.volume.resample import interpolation_matrix, resample_axes
from cubecloud_cli.volume.scan import Scan

log = logging.getLogger("cubecloud")

VOLUME_NPY = "volume.npy"
VOLUME_NIFTI = "volume.nii.gz"
PREVIEW_PNG = "preview.png"


def recorded_params(settings: PreprocessSettings) -> dict:
    """What a complete preprocess/ must have been made with to be current (with the same scan)."""
    return asdict(settings)


@dataclass(frozen=True)
class PreprocessStage(Stage):
    """The preprocess stage of a pipeline over ``scan`` (docs/design.md §1)."""

    scan: Path
    work: Path
    settings: PreprocessSettings
    runtime: Runtime = Runtime()  # its threads bound the resampling's BLAS products
    folder = "preprocess"
    upstream = ()

    def input_files(self) -> list[Path]:
        return [Path(self.scan)]

    def recorded_params(self) -> dict:
        return recorded_params(self.settings)

    def run(self, force: bool, resume: bool, on_progress: ProgressCallback) -> dict:
        self.runtime.bound_cpu_threads()
        return preprocess_scan(self.scan, self.work, self.settings, force=force, on_progress=on_progress)


def _check_memory(size: int, source_voxels: int) -> None:
    # Peak: the float32 source and its windowed copy, two intermediate products, the S³ result.
    needed = 4 * (2 * source_voxels + 3 * size**3)
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return
    if needed > 0.8 * total:
        raise CubecloudError(
            f"--size {size} needs about {needed / 2**30:.1f} GiB of memory and this machine has "
            f"{total / 2**30:.1f} GiB: choose a smaller --size"
        )


PHASES = ("read", "intensity", "resample", "write")


def phase_costs(source_voxels: int, size: int) -> dict[str, float]:
    """Expected relative cost of each phase (seconds on a 2-core CPU, from bench/preprocess.py:
    reading ~60 M source voxels/s, writing ~11 M output voxels/s, dominated by gzip)."""
    output_voxels = float(size) ** 3
    return {
        "read": source_voxels / 60e6,
        "intensity": source_voxels / 600e6,
        "resample": output_voxels / 300e6 + source_voxels / 60e6,
        "write": output_voxels / 11e6,
    }


def preprocess_scan(
    scan_path: Path,
    work: Path,
    settings: PreprocessSettings,
    *,
    force: bool = False,
    on_progress: ProgressCallback = no_progress,
) -> dict:
    """Run the stage; returns the manifest written to WORK/preprocess/manifest.json.

    ``on_progress`` counts expected seconds (:func:`phase_costs`, known once the scan's size
    is) through the phases of :data:`PHASES`.
    """

    def on_phase(phase: str, costs: dict[str, float], fraction: float) -> None:
        before = sum(costs[p] for p in PHASES[: PHASES.index(phase)])
        on_progress(phase, before + fraction * costs[phase], sum(costs.values()), {})

    settings.validate()
    writer = StageWriter(Path(work), "preprocess", recorded_params(settings), force=force)
    with writer:  # refuses an existing stage before the scan is read
        costs = phase_costs(0, settings.size if isinstance(settings.size, int) else 0)
        on_phase("read", costs, 0.0)
        with writer.phase("read"):
            scan = read_scan(
                scan_path, spacing_mm=settings.spacing, volume_index=settings.volume_index, series_uid=settings.series
            )
            writer.add_input(Path(scan_path), label=str(scan_path))
        for note in scan.notes:
            log.info(note)
        size = cube_size(scan, settings)
        warn_about_geometry(scan, size, settings.fit)  # type: ignore[arg-type]
        costs = phase_costs(scan.data.size, size)
        _check_memory(size, scan.data.size)
        check_free_disk(Path(work), 2 * 4 * size**3)

        on_phase("intensity", costs, 0.0)
        with writer.phase("intensity"):
            source_info = describe_source(scan, scan_path, replaced=replace_nonfinite_voxels(scan))
            intensity = choose_intensity_map(scan, settings)
            normalized = normalize_in_ras(scan, intensity)
            del scan

        on_phase("resample", costs, 0.0)
        with writer.phase("resample"):
            frame, volume = resample_to_cube(normalized, settings, size)
            del normalized

        on_phase("write", costs, 0.0)
        with writer.phase("write"):
            _write_volume(
                writer.directory, volume, frame, intensity, lambda fraction: on_phase("write", costs, fraction)
            )

        if not volume.any():
            log.warning(
                "the volume is all air (0 everywhere): cunerf will refuse it; check the scan, --window and --size"
            )
        writer.metrics.update(_volume_statistics(volume))
        writer.extra.update(
            {
                "source": source_info,
                "intensity": intensity.as_dict(),
                "geometry": frame.describe(),
                "volume": {"file": VOLUME_NPY, "shape": list(volume.shape), "dtype": "float32", "axes": "RAS"},
            }
        )
    return read_manifest(writer.final_dir)


def replace_nonfinite_voxels(scan: Scan) -> int:
    """Replace NaN and Inf voxels in place (the affine is untouched); returns how many there were."""
    replaced = replace_nonfinite(scan.data)
    if replaced:
        log.warning(
            f"{replaced} voxels were NaN or Inf; replaced them with the scan's "
            f"smallest (NaN, -Inf) or largest (+Inf) finite value"
        )
    return replaced


def describe_source(scan: Scan, scan_path: Path, replaced: int) -> dict:
    """The scan as read, for the manifest: its format, array shape, orientation, affine and values."""
    source_range = (float(scan.data.min()), float(scan.data.max()))
    if source_range[0] == source_range[1]:
        log.warning(
            f"the scan is constant ({source_range[0]:g} everywhere): the volume is uniform and holds no anatomy"
        )
    return {
        "path": str(Path(scan_path).resolve()),
        "format": scan.source_format,
        "shape": list(scan.data.shape),
        "axcodes": axis_codes(scan.affine),
        "spacing_mm": scan.spacing_mm,
        "affine": scan.affine,
        "value_range": source_range,
        "nonfinite_replaced": replaced,
        **({"acquisition": scan.acquisition} if scan.acquisition else {}),
    }


def choose_intensity_map(scan: Scan, settings: PreprocessSettings) -> IntensityMap:
    """The map from the scan's values to [0, 1]: a CT window or MR percentiles, by the scan's modality."""
    if settings.modality == "auto":
        modality, reason = detect_modality(scan.data, scan.modality)
        log.info(f"modality: {modality.upper()} ({reason}); override with --modality")
    else:
        modality = settings.modality
    return resolve_intensity_map(
        scan.data, modality, settings.window, settings.hu_min, settings.hu_max, settings.percentiles
    )


def normalize_in_ras(scan: Scan, intensity: IntensityMap) -> Scan:
    """The scan with its axes flipped and permuted to RAS (the affine follows, so every voxel keeps
    its scanner position) and its values mapped to [0, 1] in place."""
    data, affine = reorient_to_ras(scan.data, scan.affine)
    return Scan(
        intensity.apply(data, inplace=True), affine, scan.source_format, scan.modality, scan.notes, scan.acquisition
    )


def cube_size(scan: Scan, settings: PreprocessSettings) -> int:
    """The cube side: --size, or the one the scan's own spacing asks for (said in the log)."""
    if settings.size != SIZE_FROM_SCAN:
        return int(settings.size)
    spacing = scan.spacing_mm
    size = size_for_scan(scan.data.shape, spacing, settings.fit)  # type: ignore[arg-type]
    extent = max(n * s for n, s in zip(scan.data.shape, spacing))
    log.info(
        f"cube size {size}³ from the scan's finest spacing ({min(spacing):.3g} mm over {extent:.0f} mm, "
        f"capped at {SCAN_SIZE_CAP}); --size sets another"
    )
    return size


SHEAR_NOTED_DEGREES = 0.5


def warn_about_geometry(scan: Scan, size: int, fit: Fit) -> None:
    """One line each for a scan that the cube would make too thin to keep, and for a sheared
    affine, saying what is done and what to do."""
    shape, spacing = scan.data.shape, scan.spacing_mm
    across = voxels_across(shape, spacing, size, fit)
    thin = int(np.argmin(across))
    if across[thin] < MIN_VOXELS_ACROSS:
        keeping = size_keeping(shape, spacing)
        fix = (
            f"--size {keeping} keeps {MIN_VOXELS_ACROSS:g} voxels across it"
            if keeping
            else f"no --size up to {SCAN_SIZE_CAP} keeps {MIN_VOXELS_ACROSS:g} voxels across it: --fit stretch spreads it"
        )
        log.warning(
            f"the scan is {shape[thin]} voxels of {spacing[thin]:.3g} mm ({shape[thin] * spacing[thin]:.3g} mm) thick "
            f"along its axis {thin}: {across[thin]:.2f} voxels of the {size}³ cube, which resampling may erase; {fix}"
        )
    shear = shear_degrees(scan.affine)
    if shear > SHEAR_NOTED_DEGREES:
        log.warning(
            f"the scan's voxel axes are sheared by {shear:.1f}° (a tilted gantry?): the cube is resampled along the "
            "scan's own axes, so the 3D scene shows the anatomy unsheared, while volume.nii.gz and every length in mm "
            "(the viewer's ruler, the world-to-scanner map) keep the shear through the affine"
        )


def resample_to_cube(scan: Scan, settings: PreprocessSettings, size: int) -> tuple[CubeFrame, np.ndarray]:
    """The S³ cube the volume is resampled to (its frame replaces the affine: voxel -> world ->
    scanner), and the resampled volume."""
    frame = plan_cube(scan.data.shape, scan.affine, size, settings.fit)  # type: ignore[arg-type]
    matrices = [
        interpolation_matrix(n, size, frame.index_scale[a], frame.index_offset[a], settings.interpolation)  # type: ignore[arg-type]
        for a, n in enumerate(scan.data.shape)
    ]
    return frame, resample_axes(scan.data, matrices)


def _write_volume(
    directory: Path, volume: np.ndarray, frame: CubeFrame, intensity: IntensityMap, on_fraction: Callable[[float], None]
) -> None:
    save_array(directory / VOLUME_NPY, volume)
    write_nifti(
        volume,
        frame.voxel_to_scanner(),
        directory / VOLUME_NIFTI,
        f"cubecloud {intensity.method} -> [0,1]",
        on_progress=on_fraction,
    )
    write_preview(volume, directory / PREVIEW_PNG)


def _volume_statistics(volume: np.ndarray) -> dict[str, float]:
    return {
        "value_min": float(volume.min()),
        "value_max": float(volume.max()),
        "value_mean": float(volume.mean()),
        "nonzero_fraction": float(np.count_nonzero(volume) / volume.size),
    }
