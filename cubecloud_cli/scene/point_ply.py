"""Point-cloud PLY: the seed cloud that 3DGS trainers read as ``points3D.ply`` / ``sparse_pc.ply``.

One ``vertex`` element, binary little-endian, properties ``x y z nx ny nz`` (float32, normals
zero) then ``red green blue`` (uchar): exactly what the reference 3DGS ``storePly`` writes and
``fetchPly`` reads by name, normals included, since it fails without them (3dgs.md §1.7).
Our extra per-point values (CT intensity, density) follow as float32, which those readers
ignore.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement, PlyParseError

from cubecloud_cli.core.errors import CubecloudError

POSITION = ("x", "y", "z")
NORMAL = ("nx", "ny", "nz")
COLOUR = ("red", "green", "blue")
STANDARD = POSITION + NORMAL + COLOUR


def write_point_cloud_ply(
    path: Path, xyz: np.ndarray, rgb: np.ndarray, extra: dict[str, np.ndarray] | None = None
) -> Path:
    """Write points ``xyz`` (P, 3) with colours ``rgb`` (P, 3) uint8 and optional float columns."""
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    rgb = np.asarray(rgb)
    if rgb.shape != xyz.shape or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be uint8 with the shape of xyz {xyz.shape}, got {rgb.dtype} {rgb.shape}")
    extra = dict(extra or {})
    for name, values in extra.items():
        if name in STANDARD or not name.isidentifier():
            raise ValueError(f"extra property name {name!r} clashes with a standard one or is not an identifier")
        if np.shape(values) != (len(xyz),):
            raise ValueError(f"extra property {name!r} must be ({len(xyz)},), got {np.shape(values)}")
    dtype = [(name, "<f4") for name in POSITION + NORMAL] + [(name, "u1") for name in COLOUR]
    dtype += [(name, "<f4") for name in extra]
    vertices = np.zeros(len(xyz), dtype=dtype)  # normals stay zero
    for axis, name in enumerate(POSITION):
        vertices[name] = xyz[:, axis]
    for channel, name in enumerate(COLOUR):
        vertices[name] = rgb[:, channel]
    for name, values in extra.items():
        vertices[name] = np.asarray(values, dtype=np.float32)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(vertices, "vertex")], byte_order="<").write(str(path))
    return path


def read_point_cloud_ply(path: Path) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Points (P, 3) float64, colours (P, 3) uint8 and every other vertex property by name.

    Normals are dropped. Colours are required, as 3DGS's ``fetchPly`` requires them; a float
    colour in [0, 1] (some exporters write one) is scaled to 0..255.
    """
    path = Path(path)
    if not path.is_file():
        raise CubecloudError(f"point cloud {path} does not exist: check the path")
    try:
        ply = PlyData.read(str(path))
        vertex = ply["vertex"]
        names = [prop.name for prop in vertex.properties]
        data = vertex.data
    except KeyError:
        raise CubecloudError(f"{path} has no `vertex` element: it is not a point cloud") from None
    except (PlyParseError, ValueError, EOFError, IndexError, TypeError) as error:
        raise CubecloudError(f"{path} is not a readable PLY file ({error}); re-export it") from None
    missing = [name for name in POSITION + COLOUR if name not in names]
    if missing:
        raise CubecloudError(f"{path} lacks the vertex properties {', '.join(missing)}: re-export it with colours")
    xyz = np.stack([np.asarray(data[name], dtype=np.float64) for name in POSITION], axis=1)
    rgb = np.stack([np.asarray(data[name]) for name in COLOUR], axis=1)
    if rgb.dtype != np.uint8:
        scale = 255.0 if np.issubdtype(rgb.dtype, np.floating) and rgb.size and rgb.max() <= 1.0 else 1.0
        rgb = np.clip(np.rint(rgb.astype(np.float64) * scale), 0, 255).astype(np.uint8)
    # np.array copies: plyfile may hand out views of a memory-mapped file.
    extras = {name: np.array(data[name]) for name in names if name not in STANDARD}
    return xyz, rgb, extras
