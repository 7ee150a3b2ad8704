"""Numerical stability at the extremes (issue 7): the kernels with extreme but legal inputs, and
the whole pipeline on degenerate scans. Each case ends with finite outputs or a clear error."""

import math

import numpy as np
import pytest
import torch
from cli_helpers import invoke
from conftest import write_nifti
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from cubecloud_cli.cameras import OrbitSpec, orbit_cameras
from cubecloud_cli.raster import covariances
from cubecloud_cli.raster.backends import NUMBA, TORCH

CAMERAS = orbit_cameras(OrbitSpec(views=3, resolution=24, elevation=15.0))
quaternion = st.tuples(*[st.floats(-1, 1)] * 4)


@settings(max_examples=60, deadline=None)
@given(st.floats(-9, 4), st.floats(-9, 4), quaternion)
def test_covariances_stay_symmetric_and_positive(log_a, log_b, q):
    # Below 1e-12 in norm a quaternion is degenerate and normalised only approximately (the
    # guard that keeps its gradient finite); exactly zero is the identity.
    assume(sum(c * c for c in q) >= 1e-24 or all(c == 0 for c in q))
    scales = torch.tensor([[10.0**log_a, 10.0**log_b, 10.0 ** ((log_a + log_b) / 2)]], dtype=torch.float64)
    sigma = covariances(scales, torch.tensor([q], dtype=torch.float64))[0]
    assert torch.isfinite(sigma).all() and torch.allclose(sigma, sigma.T)
    eigenvalues = torch.linalg.eigvalsh(sigma)
    assert float(eigenvalues.min()) >= -1e-12 * max(1.0, float(eigenvalues.max()))
    assert math.isclose(float(torch.trace(sigma)), float((scales**2).sum()), rel_tol=1e-9)  # rotations keep the trace


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.floats(-1.5, 1.5),
            st.floats(-1.5, 1.5),
            st.floats(-1.5, 1.5),  # means, some behind the camera
            st.floats(-7, 1),  # log10 scale: from a point to the whole view
            st.sampled_from([0.0, 1e-6, 1.0 / 255.0, 0.5, 0.99, 1.0 - 1e-7, 1.0]),  # opacity
            quaternion,
        ),
        min_size=1,
        max_size=6,
    ),
    st.sampled_from([torch.float32, torch.float64]),
)
def test_the_rasterizers_stay_finite_and_agree_at_the_extremes(gaussians, dtype):
    means = torch.tensor([g[:3] for g in gaussians], dtype=dtype)
    scales = torch.tensor([[10.0 ** g[3]] * 3 for g in gaussians], dtype=dtype)
    opacities = torch.tensor([g[4] for g in gaussians], dtype=dtype)
    quaternions = torch.tensor([g[5] for g in gaussians], dtype=dtype)
    colours = torch.linspace(0.2, 0.9, len(gaussians), dtype=dtype)[:, None]
    rotation, translation = (torch.tensor(a, dtype=dtype) for a in (CAMERAS.rotations[1], CAMERAS.translations[1]))
    images = []
    for backend in (TORCH, NUMBA):
        inputs = [t.clone().requires_grad_(True) for t in (means, scales, opacities, colours)]
        image = backend.render(
            inputs[0], inputs[1], quaternions, inputs[2], inputs[3], rotation, translation, float(CAMERAS.focal), 24, 24
        ).image
        image.sum().backward()
        values = image.detach()
        assert torch.isfinite(values).all() and 0.0 <= float(values.min()) and float(values.max()) <= 1.0 + 1e-6
        for t in inputs:
            assert t.grad is None or torch.isfinite(t.grad).all()
        images.append(image.detach())
    # Identical opacities of exactly 0.99 stack to T = 1e-4, a tie either side may break; beyond
    # that, the two paths agree.
    if not any(g[4] >= 0.99 for g in gaussians):
        assert float((images[0] - images[1]).abs().max()) < (1e-9 if dtype == torch.float64 else 1e-4)


QUICK = ("--size", 16, "--cunerf-iterations", 20, "--views", 4, "--resolution", 16, "--splat-iterations", 6)


def _scan(tmp_path, kind):
    if kind == "float16":  # an array, as a converter might hand it over, with its spacing given
        path = tmp_path / "scan.npy"
        np.save(path, np.random.default_rng(2).uniform(-1000, 1000, (10, 12, 14)).astype(np.float16))
        return path, ("--spacing", "1,1,1")
    data, affine = {
        "constant": (np.full((12, 12, 12), 40, np.int16), np.eye(4)),
        "one voxel": (np.where(np.indices((16, 16, 16)).sum(0) == 24, 1000, -1000).astype(np.int16), np.eye(4)),
        "two slices": (
            np.random.default_rng(0).integers(-1000, 1000, (20, 20, 2)).astype(np.int16),
            np.diag([1.0, 1.0, 3.0, 1.0]),
        ),
        "anisotropic": (
            np.random.default_rng(1).integers(-1000, 1000, (40, 40, 4)).astype(np.int16),
            np.diag([0.3, 0.3, 10.0, 1.0]),
        ),
    }[kind]
    return write_nifti(tmp_path / "scan.nii.gz", data, affine), ()


def _finite(value) -> bool:
    if isinstance(value, dict):
        return all(_finite(v) for v in value.values())
    if isinstance(value, list):
        return all(_finite(v) for v in value)
    return not isinstance(value, float) or math.isfinite(value)


@pytest.mark.parametrize("kind", ["one voxel", "two slices", "anisotropic", "float16"])
def test_the_whole_pipeline_on_degenerate_scans_ends_finite(tmp_path, kind):
    import json

    scan, extra = _scan(tmp_path, kind)
    result = invoke("run", scan, "-o", tmp_path / "w", *QUICK, *extra)
    assert result.exit_code == 0, result.output
    for stage in ("preprocess", "cunerf", "export", "splat", "splat-random", "eval"):
        assert _finite(json.loads((tmp_path / "w" / stage / "manifest.json").read_text())["metrics"]), stage
    results = json.loads((tmp_path / "w" / "eval" / "metrics.json").read_text())["results"]
    for row in ("splat", "splat-random", "cunerf"):
        assert math.isfinite(results[row]["psnr"]) and -1.0 <= results[row]["ssim"] <= 1.0


def test_a_constant_scan_stops_with_a_clear_error_before_training(tmp_path):
    from cli_helpers import assert_one_line_error

    scan, _ = _scan(tmp_path, "constant")  # 40 everywhere, read as MR: a cube of 0
    assert_one_line_error(
        invoke("run", scan, "-o", tmp_path / "w", *QUICK), r"0 everywhere .*constant scan.*nothing to train"
    )
    work = tmp_path / "w"
    assert (work / "preprocess" / "manifest.json").is_file()
    assert not (work / "cunerf").exists() and not list(work.glob(".cunerf*"))  # nothing half-written
