"""Orbit and sphere cameras (docs/design.md §2): geometry, the fitted field of view, projection and its
guards; the novel-view set."""

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.cameras import OrbitSpec, PinholeCameras, orbit_cameras, sphere_cameras
from cubecloud_cli.core.errors import CubecloudError

CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
AXES = {"si": np.array([0, 0, 1.0]), "ap": np.array([0, 1.0, 0]), "lr": np.array([1.0, 0, 0])}


@pytest.mark.parametrize("axis", ["si", "ap", "lr"])
@pytest.mark.parametrize("elevation", [0.0, 30.0, -60.0])
def test_orbit_geometry(axis, elevation):
    cameras = orbit_cameras(OrbitSpec(views=12, axis=axis, radius=3.5, resolution=64, elevation=elevation))
    centres = cameras.centres()
    np.testing.assert_allclose(np.linalg.norm(centres, axis=1), 3.5, rtol=1e-12)
    # Rotations are proper, and the optical axis goes through the origin (the image centre).
    for k in range(len(cameras)):
        rotation = cameras.rotations[k]
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0)
        pixel, depth = cameras.project(k, np.zeros((1, 3)))
        np.testing.assert_allclose(pixel[0], [32.0, 32.0], atol=1e-9)
        # Image "up" is along the orbit axis: a point up the axis appears above the centre.
        up_pixel, _ = cameras.project(k, 0.5 * AXES[axis][None])
        assert up_pixel[0, 1] < 32.0 - 1.0
        assert abs(up_pixel[0, 0] - 32.0) < 1e-6
    # Evenly spread over 360°, all at the same elevation above the orbit plane.
    heights = centres @ AXES[axis]
    np.testing.assert_allclose(heights, 3.5 * math.sin(math.radians(elevation)), atol=1e-12)
    planar = centres - heights[:, None] * AXES[axis]
    cosines = np.sum(planar * np.roll(planar, -1, axis=0), axis=1) / np.sum(planar * planar, axis=1)
    np.testing.assert_allclose(cosines, math.cos(2 * math.pi / 12), atol=1e-9)


def test_first_view_looks_like_a_radiologists():
    cameras = orbit_cameras(OrbitSpec(views=4, axis="si", resolution=64))
    np.testing.assert_allclose(cameras.centres()[0], [0, 4, 0], atol=1e-12)  # from the front
    pixels, _ = cameras.project(0, np.array([[0.5, 0, 0], [0, 0, 0.5]]))
    assert pixels[0, 0] < 32  # the patient's right (+x) on the image left
    assert pixels[1, 1] < 32  # superior up
    axial = orbit_cameras(OrbitSpec(views=4, axis="ap", resolution=64))
    np.testing.assert_allclose(axial.centres()[0], [0, 0, -4], atol=1e-12)  # from the feet
    pixels, _ = axial.project(0, np.array([[0.5, 0, 0], [0, 0.5, 0]]))
    assert pixels[0, 0] < 32 and pixels[1, 1] < 32  # right on the left, anterior up


@pytest.mark.parametrize("radius", [1.8, 4.0, 50.0])
@pytest.mark.parametrize("elevation", [0.0, 45.0, 85.0])
def test_fitted_field_of_view_holds_the_whole_cube_tightly(radius, elevation):
    cameras = orbit_cameras(OrbitSpec(views=7, axis="si", radius=radius, resolution=100, elevation=elevation))
    extremes = []
    for k in range(len(cameras)):
        pixels, depth = cameras.project(k, CORNERS)
        assert (depth > 0).all()
        assert (pixels >= 0).all() and (pixels <= 100).all()
        extremes.append(np.abs(pixels - 50).max())
    assert max(extremes) == pytest.approx(50 / 1.02, rel=1e-9)  # touches the 2% margin


def test_given_fov_sets_the_focal_length():
    cameras = orbit_cameras(OrbitSpec(views=3, resolution=200, fov=60.0))
    assert cameras.focal == pytest.approx(100 / math.tan(math.radians(30)))
    assert math.degrees(cameras.fov_x) == pytest.approx(60.0)


@pytest.mark.parametrize(
    "spec, words",
    [
        (OrbitSpec(views=1), "at least 2 views"),
        (OrbitSpec(radius=1.5), "inside the volume"),
        (OrbitSpec(radius=float("nan")), "inside the volume"),
        (OrbitSpec(resolution=0), "positive number of pixels"),
        (OrbitSpec(elevation=90.0), "elevation"),
        (OrbitSpec(fov=0.0), "--fov"),
        (OrbitSpec(fov=180.0), "--fov"),
        (OrbitSpec(axis="xy"), "--axis"),
    ],
)
def test_bad_orbits_name_the_fix(spec, words):
    with pytest.raises(CubecloudError, match=words):
        orbit_cameras(spec)


def test_points_behind_the_camera_do_not_project():
    cameras = orbit_cameras(OrbitSpec(views=2, resolution=32))
    behind = cameras.centres()[0] * 1.5  # further out along the camera's own position
    on_plane = cameras.centres()[0] + np.cross(cameras.centres()[0], [0, 0, 1.0])
    pixels, depth = cameras.project(0, np.stack([behind, on_plane]))
    assert depth[0] < 0 and abs(depth[1]) < 1e-9
    assert np.isnan(pixels).all()


@settings(max_examples=60, deadline=None)
@given(
    u=st.floats(0.0, 63.999),
    v=st.floats(0.0, 63.999),
    distance=st.floats(1e-3, 1e3),
    view=st.integers(0, 4),
)
def test_projection_inverts_pixel_rays(u, v, distance, view):
    cameras = orbit_cameras(OrbitSpec(views=5, resolution=64, elevation=20.0))
    camera_point = np.array([(u - 32) / cameras.focal, (v - 32) / cameras.focal, 1.0]) * distance
    world = cameras.rotations[view].T @ (camera_point - cameras.translations[view])
    pixel, depth = cameras.project(view, world[None])
    np.testing.assert_allclose(pixel[0], [u, v], atol=1e-6 * max(1.0, distance))
    assert depth[0] == pytest.approx(distance)


def test_pixel_directions_go_through_pixel_centres():
    cameras = orbit_cameras(OrbitSpec(views=3, resolution=8, elevation=10.0))
    directions = cameras.pixel_directions(1).reshape(8, 8, 3)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=-1), 1.0, atol=1e-12)
    point = cameras.centres()[1] + 3.0 * directions[2, 5]  # row v = 2, column u = 5
    pixel, _ = cameras.project(1, point[None])
    np.testing.assert_allclose(pixel[0], [5.5, 2.5], atol=1e-9)


def test_camera_matrices_are_consistent():
    cameras = orbit_cameras(OrbitSpec(views=4, resolution=16))
    product = cameras.world_to_camera() @ cameras.camera_to_world()
    np.testing.assert_allclose(product, np.tile(np.eye(4), (4, 1, 1)), atol=1e-12)
    with pytest.raises(ValueError):
        PinholeCameras(cameras.rotations, cameras.translations, 16, 16, 0.0)


@settings(max_examples=80, deadline=None)
@given(
    radius=st.floats(1.76, 1e4),
    elevation=st.floats(-85.0, 85.0),
    views=st.integers(2, 90),
    resolution=st.integers(1, 2048),
    axis=st.sampled_from(["si", "ap", "lr"]),
)
def test_orbits_stay_finite_and_hold_the_cube_at_the_extremes(radius, elevation, views, resolution, axis):
    cameras = orbit_cameras(OrbitSpec(views, axis, radius, resolution, elevation))
    assert np.isfinite(cameras.rotations).all() and np.isfinite(cameras.translations).all()
    assert np.isfinite(cameras.focal) and cameras.focal > 0
    np.testing.assert_allclose(
        np.einsum("nij,nkj->nik", cameras.rotations, cameras.rotations), np.tile(np.eye(3), (views, 1, 1)), atol=1e-9
    )
    for view in (0, views - 1):
        pixels, depth = cameras.project(view, CORNERS)
        assert (depth > 0).all()
        assert (pixels >= -1e-6 * resolution).all() and (pixels <= resolution * (1 + 1e-6)).all()


@pytest.mark.parametrize("fov", [1.0, 170.0])
def test_extreme_fields_of_view(fov):
    cameras = orbit_cameras(OrbitSpec(views=2, resolution=16, fov=fov))
    assert math.degrees(cameras.fov_x) == pytest.approx(fov)
    assert np.isfinite(cameras.pixel_directions(1)).all()


# -- the sphere (docs/design.md §2) --------------------------------------------------------------------


def angles_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.arccos(np.clip(a @ b.T, -1.0, 1.0))


@pytest.mark.parametrize("views", [2, 3, 8, 60, 120, 333])
def test_the_sphere_is_even(views):
    """No two cameras closer than 0.8 × the spacing of N equal cells, √(4π/N), and no direction
    farther than 0.85 × that spacing from its nearest camera (a ring leaves the poles 90° away)."""
    cameras = sphere_cameras(OrbitSpec(views=views, radius=4.0, resolution=32))
    directions = cameras.centres() / 4.0
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, rtol=1e-12)
    spacing = math.sqrt(4 * math.pi / views)
    pairwise = angles_between(directions, directions)
    np.fill_diagonal(pairwise, np.inf)
    assert pairwise.min() >= 0.8 * spacing
    probes = np.random.default_rng(views).normal(size=(4000, 3))
    probes /= np.linalg.norm(probes, axis=1, keepdims=True)
    assert angles_between(probes, directions).min(axis=1).max() <= 0.85 * spacing


@pytest.mark.parametrize("axis", ["si", "ap", "lr"])
@pytest.mark.parametrize("radius", [1.8, 4.0, 50.0])
def test_every_sphere_camera_sees_the_whole_cube_and_looks_at_its_centre(axis, radius):
    cameras = sphere_cameras(OrbitSpec(views=30, axis=axis, radius=radius, resolution=64))
    extremes = []
    for k in range(len(cameras)):
        rotation = cameras.rotations[k]
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0)
        np.testing.assert_allclose(cameras.project(k, np.zeros((1, 3)))[0][0], [32.0, 32.0], atol=1e-9)
        pixels, depth = cameras.project(k, CORNERS)
        assert (depth > 0).all() and (pixels >= 0).all() and (pixels <= 64).all()
        extremes.append(np.abs(pixels - 32).max())
    assert max(extremes) == pytest.approx(32 / 1.02, rel=1e-9)


def test_the_sphere_keeps_superior_up_and_anterior_up_at_the_poles():
    cameras = sphere_cameras(OrbitSpec(views=60, axis="si", resolution=64))
    directions = cameras.centres() / 4.0
    polar = np.degrees(np.arccos(np.abs(directions[:, 2])))
    assert polar.min() < 20.0  # the lattice does reach into the pole caps
    for k in range(len(cameras)):
        probe = np.array([[0.0, 0.0, 0.5]]) if polar[k] > 20.0 else np.array([[0.0, 0.5, 0.0]])
        pixel, _ = cameras.project(k, probe)
        # Outside the caps the head is up; inside them (looking down the long axis) the front is up.
        assert pixel[0, 1] < 32.0 - 1.0 and abs(pixel[0, 0] - 32.0) < 1e-6


def test_a_camera_exactly_on_a_pole_has_a_proper_pose():
    from cubecloud_cli.cameras.sphere import POLE_UP, poses_looking_at_origin

    for direction in ([0.0, 0.0, 1.0], [0.0, 0.0, -1.0]):
        rotations, translations = poses_looking_at_origin(
            np.array([direction]), 4.0, np.array([0.0, 0.0, 1.0]), np.asarray(POLE_UP["si"])
        )
        assert np.isfinite(rotations).all() and np.linalg.det(rotations[0]) == pytest.approx(1.0)
        np.testing.assert_allclose(rotations[0][1], [0.0, -1.0, 0.0], atol=1e-12)  # image down = posterior


def test_elevation_is_refused_off_the_orbit():
    from cubecloud_cli.export.settings import ExportSettings

    with pytest.raises(CubecloudError, match="--elevation"):
        ExportSettings(cameras="sphere", elevation=10.0).validate()


# -- the novel-view test ------------------------------------------------------------------------


def test_novel_directions_are_fixed_and_start_at_the_poles():
    from cubecloud_cli.cameras.novel import novel_directions

    first, again = novel_directions(16), novel_directions(16)
    np.testing.assert_array_equal(first, again)  # the same set in every export
    np.testing.assert_allclose(np.linalg.norm(first, axis=1), 1.0, rtol=1e-12)
    np.testing.assert_array_equal(first[:2], [[0, 0, 1.0], [0, 0, -1.0]])
    np.testing.assert_array_equal(novel_directions(5), first[:5])  # a smaller set is a prefix
    assert novel_directions(0).shape == (0, 3)


@pytest.mark.parametrize(
    "cameras, views",
    [("sphere", 60), ("sphere", 30), ("sphere", 120), ("orbit", 60), ("orbit", 120), ("orbit", 30), ("sphere", 240)],
)
def test_no_novel_view_is_a_training_view(cameras, views):
    from cubecloud_cli.cameras.novel import nearest_angles_deg, novel_directions
    from cubecloud_cli.export.settings import ExportSettings

    training = ExportSettings(cameras=cameras, views=views).camera_set()
    assert nearest_angles_deg(novel_directions(16), training.centres()).min() > 1.0


def test_the_novel_set_fits_the_cube_at_magnification_one_and_round_trips():
    from cubecloud_cli.cameras.novel import NovelViewSet

    novel = NovelViewSet.build(16, 4.0, 64)
    assert len(novel) == 80 and novel.entries()[17] == ("novel_m0.75_d01", 1, 0.75)
    unit = novel.cameras(1.0)
    extremes = [np.abs(unit.project(k, CORNERS)[0] - 32).max() for k in range(16)]
    assert max(extremes) == pytest.approx(32 / 1.02, rel=1e-9)
    assert novel.cameras(2.0).focal == pytest.approx(2 * unit.focal)
    again = NovelViewSet.from_json(json.loads(json.dumps(novel.as_json())))
    for m in novel.magnifications:
        a, b = novel.cameras(m), again.cameras(m)
        np.testing.assert_allclose(a.rotations, b.rotations, atol=1e-15)
        np.testing.assert_allclose(a.translations, b.translations, atol=1e-15)
        assert a.focal == b.focal


def test_nearest_angles_ignore_cameras_at_the_origin():
    from cubecloud_cli.cameras.novel import nearest_angles_deg

    angles = nearest_angles_deg(np.array([[1.0, 0, 0], [0, 1.0, 0]]), np.array([[0.0, 0, 0], [3.0, 0, 0]]))
    np.testing.assert_allclose(angles, [0.0, 90.0], atol=1e-9)
    assert np.isnan(nearest_angles_deg(np.array([[1.0, 0, 0]]), np.zeros((2, 3)))).all()
