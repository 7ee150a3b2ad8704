"""The interop layer (cubecloud_cli.scene) read back by the tools that consume it.

pycolmap (COLMAP's own reader), readers that behave like the reference 3DGS ``colmap_loader.py``
and ``fetchPly`` (written here from the formats in 3dgs.md §1.7), plyfile, and the nerfstudio
transforms.json conventions; plus property tests of the quaternion conversions and the
refusals of the COLMAP reader.
"""

from __future__ import annotations

import json
import math
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from plyfile import PlyData

from cubecloud_cli.cameras import OrbitSpec, PinholeCameras, orbit_cameras, sphere_cameras
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.scene import (
    opengl_camera_to_world,
    quaternion_to_rotation,
    read_colmap_model,
    read_point_cloud_ply,
    rotation_to_quaternion,
    transforms_json,
    write_colmap_model,
    write_json,
    write_point_cloud_ply,
    write_test_list,
)

TEXT_FILES = ("cameras.txt", "images.txt", "points3D.txt")
# (axis, elevation °, width): every orbit axis, raised cameras, cameras over the sphere (poles
# included), and non-square images so that a swapped cx/cy or width/height cannot pass unnoticed.
SCENES = [
    ("si", 0.0, 32),
    ("si", 25.0, 32),
    ("ap", -30.0, 32),
    ("lr", 40.0, 40),
    ("sphere", 0.0, 32),
    ("sphere", 0.0, 40),
]


def make_scene(axis: str, elevation: float, width: int, points: int = 300, seed: int = 0):
    if axis == "sphere":
        orbit = sphere_cameras(OrbitSpec(views=12, axis="si", resolution=32))
    else:
        orbit = orbit_cameras(OrbitSpec(views=8, axis=axis, resolution=32, elevation=elevation))
    cameras = PinholeCameras(orbit.rotations, orbit.translations, width, 32, orbit.focal)
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-1.0, 1.0, (points, 3))
    rgb = rng.integers(0, 256, (points, 3), dtype=np.uint8)
    names = [f"view_{i:03d}.png" for i in range(len(cameras))]
    return cameras, names, xyz, rgb


@pytest.fixture(params=SCENES, ids=lambda p: f"{p[0]}-el{p[1]:g}-w{p[2]}")
def scene(request, tmp_path):
    cameras, names, xyz, rgb = make_scene(*request.param)
    model = tmp_path / "sparse" / "0"
    write_colmap_model(model, cameras, names, xyz, rgb)
    return model, cameras, names, xyz, rgb


def text_only_copy(model: Path, destination: Path) -> Path:
    destination.mkdir(parents=True)
    for name in TEXT_FILES:
        shutil.copy(model / name, destination / name)
    return destination


# ---------------------------------------------------------------------------------------- pycolmap


def test_pycolmap_reads_binary_and_text_models(scene, tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    model, cameras, names, xyz, rgb = scene
    for source in (model, text_only_copy(model, tmp_path / "text")):
        reconstruction = pycolmap.Reconstruction(str(source))
        assert len(reconstruction.cameras) == 1
        camera = reconstruction.cameras[1]
        assert camera.model.name == "PINHOLE"
        assert (camera.width, camera.height) == (cameras.width, cameras.height)
        assert np.array_equal(camera.params, [cameras.focal, cameras.focal, cameras.cx, cameras.cy])
        assert len(reconstruction.images) == len(cameras)
        for index, name in enumerate(names):
            image = reconstruction.images[index + 1]
            assert image.name == name and image.camera_id == 1
            # A property up to pycolmap 3.11, a method from 3.12 (rigs and frames).
            pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
            expected = np.hstack((cameras.rotations[index], cameras.translations[index][:, None]))
            np.testing.assert_allclose(pose.matrix(), expected, atol=1e-12)
            np.testing.assert_allclose(image.projection_center(), cameras.centres()[index], atol=1e-12)
        assert len(reconstruction.points3D) == len(xyz)
        for point_id in (1, len(xyz) // 2, len(xyz)):
            point = reconstruction.points3D[point_id]
            assert np.array_equal(point.xyz, xyz[point_id - 1])
            assert np.array_equal(point.color, rgb[point_id - 1])
            assert point.track.length() == 0


def test_model_written_by_pycolmap_reads_back(scene, tmp_path):
    """Our reader on COLMAP's own output (which in 4.x adds rigs and frames files)."""
    pycolmap = pytest.importorskip("pycolmap")
    model, cameras, names, xyz, rgb = scene
    reconstruction = pycolmap.Reconstruction(str(model))
    for folder, write in (("bin", reconstruction.write_binary), ("txt", reconstruction.write_text)):
        (tmp_path / folder).mkdir()
        write(str(tmp_path / folder))
        loaded = read_colmap_model(tmp_path / folder)
        assert loaded.image_names == names
        np.testing.assert_allclose(loaded.cameras.rotations, cameras.rotations, atol=1e-12)
        np.testing.assert_allclose(loaded.cameras.translations, cameras.translations, atol=1e-12)
        assert loaded.cameras.focal == pytest.approx(cameras.focal, abs=1e-9)
        assert np.array_equal(loaded.xyz, xyz) and np.array_equal(loaded.rgb, rgb)


# ------------------------------------------------------------- readers that behave like 3DGS's


def qvec_to_rotmat(q) -> np.ndarray:
    """The textbook Hamilton formula, independent of cubecloud_cli.scene.quaternions."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * y * y - 2 * z * z, 2 * x * y - 2 * w * z, 2 * z * x + 2 * w * y],
        [2 * x * y + 2 * w * z, 1 - 2 * x * x - 2 * z * z, 2 * y * z - 2 * w * x],
        [2 * z * x - 2 * w * y, 2 * y * z + 2 * w * x, 1 - 2 * x * x - 2 * y * y],
    ])  # fmt: skip


def unpack(stream, fmt: str):
    layout = struct.Struct("<" + fmt)
    data = stream.read(layout.size)
    assert len(data) == layout.size, "short read"
    return layout.unpack(data)


def gs_read_binary(model: Path):
    """cameras/images/points3D.bin parsed the way 3DGS's colmap_loader does, field by field."""
    with open(model / "cameras.bin", "rb") as stream:
        cameras = {}
        for _ in range(unpack(stream, "Q")[0]):
            camera_id, model_id, width, height = unpack(stream, "iiQQ")
            params = unpack(stream, "d" * {0: 3, 1: 4}[model_id])
            cameras[camera_id] = (model_id, width, height, params)
        assert stream.read() == b""
    with open(model / "images.bin", "rb") as stream:
        images = {}
        for _ in range(unpack(stream, "Q")[0]):
            image_id, *pose, camera_id = unpack(stream, "idddddddi")
            name = b""
            while (char := stream.read(1)) != b"\x00":
                name += char
            (count,) = unpack(stream, "Q")
            unpack(stream, "ddq" * count)
            images[image_id] = (pose[:4], pose[4:], camera_id, name.decode())
        assert stream.read() == b""
    with open(model / "points3D.bin", "rb") as stream:
        points = {}
        for _ in range(unpack(stream, "Q")[0]):
            point_id, x, y, z, r, g, b, _error = unpack(stream, "QdddBBBd")
            (track,) = unpack(stream, "Q")
            unpack(stream, "ii" * track)
            points[point_id] = ((x, y, z), (r, g, b))
        assert stream.read() == b""
    return cameras, images, points


def gs_read_text(model: Path):
    """The .txt fallback of 3DGS: PINHOLE only, and the line after an image line is its 2D points."""
    cameras = {}
    for line in (model / "cameras.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            fields = line.split()
            assert fields[1] == "PINHOLE", "3DGS's text reader asserts PINHOLE"
            cameras[int(fields[0])] = (1, int(fields[2]), int(fields[3]), tuple(map(float, fields[4:])))
    images = {}
    with open(model / "images.txt") as stream:
        while line := stream.readline():
            line = line.strip()
            if line and not line.startswith("#"):
                fields = line.split()
                points2d = stream.readline().split()  # consumed whatever it holds
                assert points2d == []
                pose = tuple(map(float, fields[1:8]))
                images[int(fields[0])] = (pose[:4], pose[4:], int(fields[8]), fields[9])
    points = {}
    for line in (model / "points3D.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            fields = line.split()
            float(fields[7])  # the error must parse
            points[int(fields[0])] = (tuple(map(float, fields[1:4])), tuple(map(int, fields[4:7])))
    return cameras, images, points


@pytest.mark.parametrize("reader", [gs_read_binary, gs_read_text])
def test_3dgs_style_readers_recover_everything_exactly(scene, reader):
    model, cameras, names, xyz, rgb = scene
    read_cameras, read_images, read_points = reader(model)
    params = (cameras.focal, cameras.focal, cameras.cx, cameras.cy)
    assert read_cameras == {1: (1, cameras.width, cameras.height, params)}
    assert sorted(read_images) == list(range(1, len(cameras) + 1))
    for index, name in enumerate(names):
        qvec, tvec, camera_id, read_name = read_images[index + 1]
        assert (camera_id, read_name) == (1, name)
        assert qvec[0] >= 0.0
        assert np.array_equal(tvec, cameras.translations[index])  # bit-exact: the text holds repr()s
        np.testing.assert_allclose(qvec_to_rotmat(qvec), cameras.rotations[index], atol=1e-12)
        assert tuple(qvec) == tuple(rotation_to_quaternion(cameras.rotations[index]))
    assert sorted(read_points) == list(range(1, len(xyz) + 1))
    assert np.array_equal([read_points[i + 1][0] for i in range(len(xyz))], xyz)
    assert np.array_equal([read_points[i + 1][1] for i in range(len(xyz))], rgb)


def test_binary_sizes_and_text_layout(scene):
    model, cameras, names, xyz, _ = scene
    assert (model / "cameras.bin").stat().st_size == 8 + 24 + 4 * 8
    assert (model / "points3D.bin").stat().st_size == 8 + len(xyz) * (8 + 24 + 3 + 8 + 8)
    expected_images = 8 + sum(64 + len(name) + 1 + 8 for name in names)
    assert (model / "images.bin").stat().st_size == expected_images
    lines = (model / "images.txt").read_text().split("\n")
    assert f"# Number of images: {len(names)}, mean observations per image: 0" in lines
    data = [i for i, line in enumerate(lines) if line and not line.startswith("#")]
    assert len(data) == len(names) and all(lines[i + 1] == "" for i in data)


def test_our_reader_round_trips_binary_text_and_scene_root(scene, tmp_path):
    model, cameras, names, xyz, rgb = scene
    for source in (model, text_only_copy(model, tmp_path / "text"), model.parent.parent):
        loaded = read_colmap_model(source)
        assert loaded.image_names == names
        assert np.array_equal(loaded.cameras.translations, cameras.translations)
        np.testing.assert_allclose(loaded.cameras.rotations, cameras.rotations, atol=1e-15)
        assert (loaded.cameras.width, loaded.cameras.height, loaded.cameras.focal) == (
            cameras.width, cameras.height, cameras.focal
        )  # fmt: skip
        assert np.array_equal(loaded.xyz, xyz) and np.array_equal(loaded.rgb, rgb)
        assert loaded.xyz.dtype == np.float64 and loaded.rgb.dtype == np.uint8


def test_reader_sorts_by_name_and_tolerates_missing_points(tmp_path):
    cameras, names, xyz, rgb = make_scene("si", 10.0, 32)
    shuffled = [f"z{7 - i}.jpg" for i in range(len(cameras))]  # written in reverse name order
    write_colmap_model(tmp_path, cameras, shuffled, xyz, rgb)
    (tmp_path / "points3D.bin").unlink()
    (tmp_path / "points3D.txt").unlink()
    loaded = read_colmap_model(tmp_path)
    assert loaded.image_names == sorted(shuffled)
    np.testing.assert_allclose(loaded.cameras.centres(), cameras.centres()[::-1], atol=1e-12)
    assert loaded.xyz.shape == (0, 3) and loaded.rgb.shape == (0, 3)


def test_reader_accepts_simple_pinhole_and_repeated_identical_cameras(tmp_path):
    cameras, names, xyz, rgb = make_scene("ap", 0.0, 32)
    write_colmap_model(tmp_path, cameras, names, xyz, rgb, binary=False)
    f = float(cameras.focal)
    # Camera 2 is PINHOLE with its principal point off by less than the 0.5 px tolerance.
    lines = f"1 SIMPLE_PINHOLE 32 32 {f!r} 16 16\n2 PINHOLE 32 32 {f!r} {f!r} 16.2 15.9\n"
    (tmp_path / "cameras.txt").write_text(lines)
    images = (tmp_path / "images.txt").read_text().replace(" 1 view_003.png", " 2 view_003.png")
    (tmp_path / "images.txt").write_text(images)
    loaded = read_colmap_model(tmp_path)
    assert loaded.cameras.focal == f and len(loaded.cameras) == len(cameras)


def test_reader_skips_tracks_and_2d_points(tmp_path):
    """Real COLMAP output has observations: variable-length records our own files never contain."""
    cameras, names, xyz, rgb = make_scene("si", 0.0, 32, points=3)
    write_colmap_model(tmp_path, cameras, names, xyz, rgb)
    tracks = [2, 0, 1]
    points = [struct.pack("<Q", 3)]
    for i, track in enumerate(tracks):
        points.append(struct.pack("<QdddBBBdQ", i + 1, *xyz[i], *rgb[i], 0.5, track) + struct.pack("<ii", 1, 0) * track)
    (tmp_path / "points3D.bin").write_bytes(b"".join(points))
    images = bytearray((tmp_path / "images.bin").read_bytes())
    first_end = 8 + 64 + len(names[0]) + 1  # where image 1's n_points2D sits
    images[first_end : first_end + 8] = struct.pack("<Q", 2)
    images[first_end + 8 : first_end + 8] = struct.pack("<ddq", 1.5, 2.5, 1) + struct.pack("<ddq", 3.0, 4.0, -1)
    (tmp_path / "images.bin").write_bytes(bytes(images))
    loaded = read_colmap_model(tmp_path)
    assert loaded.image_names == names
    assert np.array_equal(loaded.xyz, xyz) and np.array_equal(loaded.rgb, rgb)

    text = text_only_copy(tmp_path, tmp_path / "text")
    lines = (text / "points3D.txt").read_text().split("\n")
    lines[3] += " 1 0 2 5"  # a ragged track on the first point
    (text / "points3D.txt").write_text("\n".join(lines))
    assert np.array_equal(read_colmap_model(text).xyz, xyz)


def test_test_list(tmp_path):
    path = write_test_list(tmp_path / "sparse" / "0", ["a.png", "b.png"])
    assert path.read_text() == "a.png\nb.png\n"


# ------------------------------------------------------------------------------------ reader errors


def refuses(source: Path, *words: str) -> None:
    with pytest.raises(CubecloudError) as caught:
        read_colmap_model(source)
    message = str(caught.value)
    assert "\n" not in message
    for word in words:
        assert word in message


def test_reader_refuses_damaged_or_unsupported_models(tmp_path):
    cameras, names, xyz, rgb = make_scene("lr", 20.0, 32)
    write_colmap_model(tmp_path / "m", cameras, names, xyz, rgb)
    refuses(tmp_path / "absent", "does not exist")
    (tmp_path / "empty").mkdir()
    refuses(tmp_path / "empty", "no COLMAP model")

    for name, cut in (("cameras.bin", 5), ("images.bin", 3), ("points3D.bin", 7)):
        broken = tmp_path / f"cut-{name}"
        shutil.copytree(tmp_path / "m", broken)
        data = (broken / name).read_bytes()
        (broken / name).write_bytes(data[:-cut])
        refuses(broken, name, "truncated")

    text = text_only_copy(tmp_path / "m", tmp_path / "distorted")
    (text / "cameras.txt").write_text("1 SIMPLE_RADIAL 32 32 30.0 16 16 0.01\n")
    refuses(text, "SIMPLE_RADIAL", "colmap image_undistorter")

    binary = tmp_path / "opencv-bin"
    shutil.copytree(tmp_path / "m", binary)
    (binary / "cameras.bin").write_bytes(struct.pack("<QiiQQ8d", 1, 1, 4, 32, 32, 30, 30, 16, 16, 0, 0, 0, 0))
    refuses(binary, "OPENCV", "colmap image_undistorter")

    for label, line in (
        ("off-centre", "1 PINHOLE 32 32 30.0 30.0 20.0 16.0"),
        ("non-square", "1 PINHOLE 32 32 30.0 33.0 16.0 16.0"),
        ("wrong-count", "1 PINHOLE 32 32 30.0 16.0 16.0"),
    ):
        (text / "cameras.txt").write_text(line + "\n")
        with pytest.raises(CubecloudError, match="cameras.txt"):
            read_colmap_model(text)

    (text / "cameras.txt").write_text("1 PINHOLE 32 32 30 30 16 16\n2 PINHOLE 32 32 40 40 16 16\n")
    (text / "images.txt").write_text((text / "images.txt").read_text().replace(" 1 view_002.png", " 2 view_002.png"))
    refuses(text, "focal lengths differ")
    (text / "images.txt").write_text((text / "images.txt").read_text().replace(" 2 view_002.png", " 9 view_002.png"))
    refuses(text, "camera ids [9]")


def test_reader_refuses_a_zero_quaternion(tmp_path):
    cameras, names, xyz, rgb = make_scene("si", 0.0, 32)
    write_colmap_model(tmp_path, cameras, names, xyz, rgb, binary=False)
    lines = (tmp_path / "images.txt").read_text().split("\n")
    index = next(i for i, line in enumerate(lines) if line.endswith("view_004.png"))
    fields = lines[index].split()
    lines[index] = " ".join([fields[0], "0", "0", "0", "0", *fields[5:]])
    (tmp_path / "images.txt").write_text("\n".join(lines))
    refuses(tmp_path, "view_004.png", "zero")


def test_writer_rejects_bad_input(tmp_path):
    cameras, names, xyz, rgb = make_scene("si", 0.0, 32)
    with pytest.raises(ValueError, match="white space"):
        write_colmap_model(tmp_path, cameras, ["a b.png", *names[1:]], xyz, rgb)
    with pytest.raises(ValueError, match="image names"):
        write_colmap_model(tmp_path, cameras, names[:-1], xyz, rgb)
    with pytest.raises(ValueError, match="NaN"):
        write_colmap_model(tmp_path, cameras, names, np.full_like(xyz, np.nan), rgb)


# ---------------------------------------------------------------------------------------------- PLY


def test_point_cloud_ply_has_what_3dgs_reads(tmp_path):
    _, _, xyz, rgb = make_scene("si", 0.0, 32)
    rng = np.random.default_rng(1)
    extra = {"intensity": rng.uniform(-1000, 3000, len(xyz)), "density": rng.uniform(0, 1, len(xyz))}
    path = write_point_cloud_ply(tmp_path / "points3D.ply", xyz, rgb, extra)

    ply = PlyData.read(str(path))
    assert [element.name for element in ply.elements] == ["vertex"] and not ply.text
    assert ply.byte_order == "<"
    vertex = ply["vertex"]
    layout = [(prop.name, vertex.data.dtype[prop.name].str) for prop in vertex.properties]
    floats = ["x", "y", "z", "nx", "ny", "nz"]
    assert layout == [(n, "<f4") for n in floats] + [(n, "|u1") for n in ("red", "green", "blue")] + [
        ("intensity", "<f4"), ("density", "<f4")
    ]  # fmt: skip
    # What fetchPly does: positions, colours / 255 and normals, all by name.
    positions = np.vstack([vertex["x"], vertex["y"], vertex["z"]]).T
    colours = np.vstack([vertex["red"], vertex["green"], vertex["blue"]]).T / 255.0
    normals = np.vstack([vertex["nx"], vertex["ny"], vertex["nz"]]).T
    np.testing.assert_array_equal(positions, xyz.astype(np.float32))
    np.testing.assert_array_equal(colours, rgb / 255.0)
    assert not normals.any()

    read_xyz, read_rgb, extras = read_point_cloud_ply(path)
    np.testing.assert_array_equal(read_xyz, xyz.astype(np.float32))
    np.testing.assert_array_equal(read_rgb, rgb)
    assert sorted(extras) == ["density", "intensity"]
    for name, values in extra.items():
        np.testing.assert_array_equal(extras[name], values.astype(np.float32))


def opensplat_fast_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """OpenSplat 1.1.5's binary PLY reader (point_io.cpp, fastPlyReadPointSet), which reads the
    file that transforms.json's ply_file_path names: x y z first, then by position alone 3 float
    normals if any property is called nx, 3 uchar colours if any is called red, a uchar if any is
    called views. Any other property shifts every point after the first, so this re-implementation
    refuses a record size other than the one it assumes, instead of misreading."""
    data = path.read_bytes()
    header_end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:header_end].decode("ascii").splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    rest = [line for line in lines[2:] if not line.startswith(("comment", "obj_info"))]
    assert rest[0].startswith("element vertex ")
    count = int(rest[0].split()[2])
    properties = [line.split() for line in rest[1:] if line.startswith("property")]
    assert [p[-1] for p in properties[:3]] == ["x", "y", "z"]  # checkHeader
    names = [p[-1] for p in properties]
    normals, colours, views = "nx" in names, "red" in names, "views" in names
    assumed = 12 + 12 * normals + 3 * colours + 1 * views
    sizes = {"float": 4, "float32": 4, "uchar": 1, "uint8": 1, "double": 8, "int": 4, "int32": 4}
    actual = sum(sizes[p[1]] for p in properties)
    assert actual == assumed, f"OpenSplat reads {assumed}-byte points, the file has {actual}-byte ones"
    record = np.dtype(
        [("xyz", "<f4", 3)]
        + ([("normal", "<f4", 3)] if normals else [])
        + ([("rgb", "u1", 3)] if colours else [])
        + ([("views", "u1")] if views else [])
    )
    points = np.frombuffer(data, dtype=record, count=count, offset=header_end)
    return points["xyz"], points["rgb"] if colours else None


def test_the_plain_point_cloud_opens_in_opensplat_and_ours_with_extras_would_not(tmp_path):
    _, _, xyz, rgb = make_scene("si", 0.0, 32)
    plain = write_point_cloud_ply(tmp_path / "sparse_pc.ply", xyz, rgb)
    read_xyz, read_rgb = opensplat_fast_ply(plain)
    np.testing.assert_array_equal(read_xyz, xyz.astype(np.float32))
    np.testing.assert_array_equal(read_rgb, rgb)
    extras = write_point_cloud_ply(tmp_path / "points3D.ply", xyz, rgb, {"intensity": np.zeros(len(xyz))})
    with pytest.raises(AssertionError, match="OpenSplat reads 27-byte points"):
        opensplat_fast_ply(extras)


def test_point_cloud_ply_errors(tmp_path):
    with pytest.raises(CubecloudError, match="does not exist"):
        read_point_cloud_ply(tmp_path / "nope.ply")
    path = write_point_cloud_ply(tmp_path / "p.ply", np.zeros((50, 3)), np.zeros((50, 3), np.uint8))
    path.write_bytes(path.read_bytes()[:-20])
    with pytest.raises(CubecloudError, match="not a readable PLY"):
        read_point_cloud_ply(path)
    (tmp_path / "junk.ply").write_bytes(b"not a ply at all\n")
    with pytest.raises(CubecloudError):
        read_point_cloud_ply(tmp_path / "junk.ply")
    with pytest.raises(ValueError, match="clashes"):
        write_point_cloud_ply(tmp_path / "q.ply", np.zeros((2, 3)), np.zeros((2, 3), np.uint8), {"red": np.zeros(2)})


# -------------------------------------------------------------------------------------- quaternions


def axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' formula, independent of the quaternion code under test."""
    k = axis / np.linalg.norm(axis)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross


def hamilton_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """q v q* with the Hamilton product written out: pins the convention, not just consistency."""

    def product(a, b):
        w1, x1, y1, z1 = a
        w2, x2, y2, z2 = b
        return np.array([
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ])  # fmt: skip

    conjugate = q * np.array([1, -1, -1, -1])
    return product(product(q, np.concatenate(([0.0], v))), conjugate)[1:]


axes = st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 3).map(np.array).filter(lambda a: np.linalg.norm(a) > 1e-3)
angles = st.one_of(
    st.floats(0, math.pi),
    st.sampled_from([0.0, math.pi, math.pi - 1e-12, math.pi - 1e-7, 1e-12]),
    st.floats(math.pi - 1e-4, math.pi),
)


@settings(max_examples=300, deadline=None)
@given(axis=axes, angle=angles)
def test_quaternion_round_trip(axis, angle):
    rotation = axis_angle_matrix(axis, angle)
    q = rotation_to_quaternion(rotation)
    assert q.shape == (4,) and q[0] >= 0.0
    assert abs(np.linalg.norm(q) - 1.0) < 1e-12
    np.testing.assert_allclose(quaternion_to_rotation(q), rotation, atol=1e-9)
    expected = np.concatenate(([math.cos(angle / 2)], math.sin(angle / 2) * axis / np.linalg.norm(axis)))
    assert min(np.abs(q - expected).max(), np.abs(q + expected).max()) < 1e-9
    v = np.array([0.3, -1.2, 2.0])
    np.testing.assert_allclose(hamilton_rotate(q, v), rotation @ v, atol=1e-9)


def test_quaternions_vectorised_identity_and_zero():
    rotations = np.stack([np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])])
    q = rotation_to_quaternion(rotations)
    np.testing.assert_array_equal(q, [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    assert not np.signbit(q).any()  # no "-0.0" in the files
    np.testing.assert_allclose(quaternion_to_rotation(q * 3.0), rotations, atol=1e-15)  # normalised first
    with pytest.raises(ValueError, match="zero"):
        quaternion_to_rotation(np.zeros(4))
    with pytest.raises(ValueError, match="not a rotation"):
        rotation_to_quaternion(np.diag([1.0, 1.0, -1.0]))  # a reflection


# --------------------------------------------------------------------------------- transforms.json


def test_transforms_json_follows_nerfstudio(scene, tmp_path):
    _, cameras, names, _, _ = scene
    paths = [f"images/{name}" for name in names]
    test = paths[::4]
    train = [p for p in paths if p not in test]
    content = transforms_json(
        cameras, paths, train_file_paths=train, test_file_paths=test, ply_file_path="sparse_pc.ply"
    )
    content = json.loads(write_json(tmp_path / "transforms.json", content).read_text())

    assert content["camera_model"] == "PINHOLE"
    assert (content["w"], content["h"], content["cx"], content["cy"]) == (cameras.width, 32, cameras.width / 2, 16.0)
    assert content["fl_x"] == content["fl_y"] == cameras.focal
    assert content["camera_angle_x"] == pytest.approx(cameras.fov_x)
    assert cameras.width / (2 * math.tan(content["camera_angle_x"] / 2)) == pytest.approx(cameras.focal)
    assert content["camera_angle_y"] == pytest.approx(cameras.fov_y)
    assert all(content[k] == 0 for k in ("k1", "k2", "p1", "p2"))
    assert content["applied_transform"] == np.eye(4)[:3].tolist()
    assert content["ply_file_path"] == "sparse_pc.ply"
    assert content["train_filenames"] == train and content["test_filenames"] == content["val_filenames"] == test

    assert [frame["file_path"] for frame in content["frames"]] == paths
    assert [frame["colmap_im_id"] for frame in content["frames"]] == list(range(1, len(paths) + 1))
    c2w = np.array([frame["transform_matrix"] for frame in content["frames"]])
    np.testing.assert_allclose(c2w, cameras.camera_to_world() @ np.diag([1, -1, -1, 1]), atol=0)
    np.testing.assert_allclose(c2w, opengl_camera_to_world(cameras))
    # OpenGL cameras look down −z: every orbit camera looks at the origin.
    forward = -c2w[:, :3, 2]
    towards_origin = -c2w[:, :3, 3] / np.linalg.norm(c2w[:, :3, 3], axis=1, keepdims=True)
    np.testing.assert_allclose(forward, towards_origin, atol=1e-12)


def test_transforms_json_split_handling():
    cameras, names, _, _ = make_scene("si", 0.0, 32)
    content = transforms_json(cameras, names)
    assert not any(key.endswith("_filenames") for key in content) and "ply_file_path" not in content
    completed = transforms_json(cameras, names, test_file_paths=names[:2])
    assert completed["train_filenames"] == names[2:]
    with pytest.raises(ValueError, match="not one of the frames"):
        transforms_json(cameras, names, test_file_paths=["other.png"])
