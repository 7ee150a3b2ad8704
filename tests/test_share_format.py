"""`cubecloud share`'s files: SPZ written and read back (by us and by gsply, an independent reader),
at the extremes of every quantized attribute, and the page's frame, camera and assembly."""

import base64
import gzip
import json
import math
import re

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.cameras import PinholeCameras
from cubecloud_cli.cameras.orbit import OrbitSpec
from cubecloud_cli.cameras.sphere import sphere_cameras
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.share.page import (
    page_camera,
    page_info,
    patient_axes,
    read_scalar_block,
    render_page,
    scalar_block,
)
from cubecloud_cli.share.shared_scene import position_bits
from cubecloud_cli.share.spz import FRACTIONAL_BITS, decode_spz, encode_spz, smallest_three
from cubecloud_cli.splat.gaussians import Gaussians
from cubecloud_cli.transfer.function import TransferFunction
from cubecloud_cli.view.transfer_view import DrawnValues


def random_gaussians(count: int, seed: int = 0, channels: int = 1) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    return Gaussians(
        torch.rand(count, 3, generator=g) * 2 - 1,
        torch.rand(count, 3, generator=g) * 6 - 8,
        torch.randn(count, 4, generator=g),
        torch.randn(count, generator=g) * 3,
        torch.rand(count, 1, channels, generator=g) * 3 - 1.5,
        torch.zeros(count, 0, channels),
    )


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles between the rotations of (N, 4) quaternions, any length, either sign."""
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.degrees(2 * np.arccos(np.clip(np.abs((a * b).sum(axis=1)), 0, 1)))


def test_each_attribute_comes_back_within_its_quantization_step():
    gaussians = random_gaussians(2000)
    scene = decode_spz(encode_spz(gaussians, antialiased=True))
    back = scene.gaussians
    assert scene.antialiased and scene.fractional_bits == FRACTIONAL_BITS
    assert np.abs(back.means.numpy() - gaussians.means.numpy()).max() <= 0.5 / 2**FRACTIONAL_BITS + 1e-7
    assert np.abs(back.log_scales.numpy() - gaussians.log_scales.numpy()).max() <= 0.5 / 16 + 1e-6
    alpha = torch.sigmoid(gaussians.opacity_logits).numpy()
    assert np.abs(torch.sigmoid(back.opacity_logits).numpy() - alpha).max() <= 0.5 / 255 + 1e-6
    grey = back.sh_dc[:, 0, :].numpy()
    assert grey.shape[1] == 3 and np.array_equal(grey[:, 0], grey[:, 2])  # a grey scene is RGB alike
    assert np.abs(grey[:, 0] - gaussians.sh_dc[:, 0, 0].numpy()).max() <= 0.5 / (255 * 0.15) + 1e-6
    # 9 bits per component over [0, 1/√2]: under half a degree of rotation.
    assert rotation_angle_deg(back.quaternions.numpy(), gaussians.quaternions.numpy()).max() < 0.5


def test_an_independent_reader_reads_what_we_write(tmp_path):
    gsply = pytest.importorskip("gsply")
    gaussians = random_gaussians(500, seed=3)
    data = encode_spz(gaussians, antialiased=False, fractional_bits=12)
    (tmp_path / "scene.spz").write_bytes(data)
    theirs = gsply.read_spz(tmp_path / "scene.spz")
    ours = decode_spz(data).gaussians
    assert np.allclose(theirs.means, ours.means.numpy(), atol=1e-6)
    assert np.allclose(theirs.scales, ours.log_scales.numpy(), atol=1e-6)
    theirs_alpha = torch.sigmoid(torch.from_numpy(np.asarray(theirs.opacities, dtype=np.float64).reshape(-1)))
    assert np.allclose(theirs_alpha.numpy(), torch.sigmoid(ours.opacity_logits.double()).numpy(), atol=1e-5)
    assert np.allclose(theirs.sh0, ours.sh_dc[:, 0, :].numpy(), atol=1e-6)
    assert rotation_angle_deg(np.asarray(theirs.quats), ours.quaternions.numpy()).max() < 1e-3


def test_the_header_says_anti_aliased_and_nothing_else_changes_between_two_writes():
    gaussians = random_gaussians(10)
    flagged, plain = (gzip.decompress(encode_spz(gaussians, antialiased=a)) for a in (True, False))
    assert flagged[:4] == b"NGSP" and flagged[14] == 1 and plain[14] == 0
    assert flagged[15:] == plain[15:]
    assert encode_spz(gaussians, True) == encode_spz(gaussians, True)  # no time stamp in the gzip header


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(-1e30, 1e30), min_size=4, max_size=4),
    st.floats(-1e6, 1e6),
    st.floats(-50, 50),
    st.floats(-1e4, 1e4),
)
def test_extreme_values_clamp_to_the_formats_range_and_never_wrap(quaternion, position, log_scale, logit):
    gaussians = Gaussians(
        torch.full((1, 3), position),
        torch.full((1, 3), log_scale),
        torch.tensor([quaternion], dtype=torch.float64).float(),
        torch.tensor([logit]),
        torch.full((1, 1, 1), logit),
        torch.zeros(1, 0, 1),
    )
    if not torch.isfinite(gaussians.quaternions).all():
        return  # float32 overflow of the drawn values: the next test's case
    back = decode_spz(encode_spz(gaussians, antialiased=True, fractional_bits=12)).gaussians
    limit = 2**23 / 2**12
    assert np.all(np.abs(back.means.numpy() - np.clip(position, -limit, limit - 2**-12)) <= 2**-12)
    assert np.all(np.abs(back.log_scales.numpy() - np.clip(log_scale, -10, 255 / 16 - 10)) <= 1 / 32 + 1e-6)
    assert torch.isfinite(back.opacity_logits).all() and torch.isfinite(back.sh_dc).all()
    norm = float(back.quaternions.norm())
    assert abs(norm - 1) < 1e-3  # a zero or huge quaternion still comes back a rotation


def test_a_scene_with_nan_is_refused_not_written():
    gaussians = random_gaussians(4)
    gaussians.means[2, 1] = float("nan")
    with pytest.raises(CubecloudError, match="NaN or Inf.*cubecloud splat"):
        encode_spz(gaussians, antialiased=True)


@pytest.mark.parametrize(
    "damage",
    [b"not gzip at all", gzip.compress(b"NGSP", mtime=0), lambda d: gzip.compress(gzip.decompress(d)[:-1])],
    ids=["not gzip", "a header cut short", "a body a byte short"],
)
def test_a_damaged_file_is_a_one_line_error(damage):
    data = encode_spz(random_gaussians(3), antialiased=True)
    with pytest.raises(CubecloudError, match="SPZ"):
        decode_spz(damage(data) if callable(damage) else damage)


def test_the_smallest_three_drop_the_largest_component_and_keep_the_rotation():
    identity = smallest_three(np.array([[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, -2.0]]))
    assert list(identity >> 30) == [3, 3] and list(identity & ((1 << 30) - 1)) == [0, 0]
    x_turn = smallest_three(np.array([[1.0, 0.0, 0.0, 0.0]]))
    assert int(x_turn[0]) >> 30 == 0


def test_position_bits_resolve_a_sixty_fourth_of_a_voxel():
    assert position_bits(128) == 12 and position_bits(512) == 14
    assert position_bits(0) == position_bits(512)  # unknown: the finest cube
    for side in (32, 100, 128, 384):
        assert 2.0 ** -position_bits(side) <= (2.0 / side) / 64


def test_patient_axes_follow_the_scanner_map():
    assert patient_axes(np.diag([183.0, 183.0, 183.0, 1.0])) == ([["L", "R"], ["P", "A"], ["I", "S"]], [0, 1, 2])
    lps = np.diag([-1.0, -1.0, 1.0, 1.0])  # world x runs to the left
    assert patient_axes(lps)[0][:2] == [["R", "L"], ["A", "P"]]
    swapped = np.array([[0, 1.0, 0, 0], [1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1]])
    assert patient_axes(swapped) == ([["P", "A"], ["L", "R"], ["I", "S"]], [1, 0, 2])
    assert patient_axes(None)[0][0] == ["-x", "+x"]


def test_the_page_camera_is_the_exports_first_view_in_three_js_terms():
    cameras = sphere_cameras(OrbitSpec(views=4, radius=3.0, resolution=64))
    camera = page_camera(cameras, 1)
    rotation, translation = cameras.rotations[1], cameras.translations[1]
    assert np.allclose(camera.position, -rotation.T @ translation)
    assert np.allclose(camera.up, -rotation[1])
    assert np.allclose(camera.target, 0.0, atol=1e-6)  # a sphere camera looks at the origin
    assert math.isclose(camera.fov_y_degrees, math.degrees(cameras.fov_x))  # square views


def test_the_page_holds_the_scene_and_nothing_ends_its_scripts_early():
    gaussians = random_gaussians(50)
    spz = encode_spz(gaussians, antialiased=True)
    cameras = PinholeCameras(np.eye(3)[None], np.array([[0.0, 0.0, 3.0]]), 32, 32, 40.0)
    info = page_info(page_camera(cameras), np.diag([2.0, 2.0, 2.0, 1.0]), True, gaussians.log_scales.numpy())
    info["note"] = "</script><script>alert(1)</script>"
    page = render_page(spz, info)
    assert page.lower().count("</script") == 5  # the five of the template, none from the data
    embedded = re.search(r'id="scene-spz">([^<]*)<', page).group(1)
    assert base64.b64decode(embedded) == spz
    shown = json.loads(re.search(r'id="scene-info">(.*?)</script>', page, re.S).group(1))
    assert shown["note"] == info["note"] and shown["blur"] == {"mip": 0.1, "dilation": 0.0}
    assert shown["cutAxes"] == {"sagittal": 0, "coronal": 1, "axial": 2}
    assert "/*VENDOR*/" not in page and "CubecloudVendor" in page and "MIT License" in page


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=1, max_size=20),
    st.lists(st.floats(-30, 30), min_size=1, max_size=20),
)
def test_a_scalar_scenes_values_come_back_for_the_page_within_their_steps(values, log_lengths):
    count = min(len(values), len(log_lengths))
    values = np.asarray(values[:count], dtype=np.float32)
    lengths = np.exp(np.asarray(log_lengths[:count])).astype(np.float32)
    attenuation = np.linspace(0.0, 1.0, count, dtype=np.float32)
    back = read_scalar_block(scalar_block(DrawnValues(values, lengths, attenuation)))
    expected_values = np.clip(np.nan_to_num(values), 0.0, 1.0)
    assert np.abs(back.values - expected_values).max() <= 0.5 / 65535 + 1e-7
    clamped = np.clip(np.asarray(log_lengths[:count]), -10.0, 10.0)
    assert np.abs(np.log(back.lengths) - clamped).max() <= 0.5 / 2048 + 1e-5
    assert np.abs(back.attenuation - attenuation).max() <= 0.5 / 65535 + 1e-7
    tissue = TransferFunction(0.3, 0.6, 40.0)
    assert np.isfinite(back.opacities(tissue)).all()
