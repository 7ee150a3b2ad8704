"""A voxel grid read trilinearly, in numba: one definition for the dvr march
(``render/grid_march.py``) and for the scan values a scalar scene's Gaussians are held to
(``splat/losses.py``).

Corners outside the grid count as 0, as ``grid_sample``'s zero padding with
``align_corners=False`` does. On a CPU ``grid_sample`` read the 50,000 centres of a scalar scene
in 8 ms a step, about a third of the step; this kernel reads them in 3 ms (the centres come in no
order, so most corners miss the cache), which is why the trainer reads them every 10 steps.

``trilinear`` is inlined into ``render/grid_march.py``'s kernels: after editing it, touch that file
too, since numba's cache checks only the file of the kernel it caches (``numerics/jit.py``).
"""

from __future__ import annotations

import math

from numba import njit, prange

from cubecloud_cli.numerics.jit import PRANGE_ONLY


@njit(cache=True, inline="always")
def _inside(volume, ix, iy, iz, fx, fy, fz):
    """The trilinear read from low corner (ix, iy, iz) at fractions (fx, fy, fz), every corner in the grid."""
    c00 = volume[ix, iy, iz] * (1.0 - fx) + volume[ix + 1, iy, iz] * fx
    c01 = volume[ix, iy + 1, iz] * (1.0 - fx) + volume[ix + 1, iy + 1, iz] * fx
    c10 = volume[ix, iy, iz + 1] * (1.0 - fx) + volume[ix + 1, iy, iz + 1] * fx
    c11 = volume[ix, iy + 1, iz + 1] * (1.0 - fx) + volume[ix + 1, iy + 1, iz + 1] * fx
    return (c00 * (1.0 - fy) + c01 * fy) * (1.0 - fz) + (c10 * (1.0 - fy) + c11 * fy) * fz


@njit(cache=True, inline="always")
def trilinear(volume, x, y, z):
    """The grid's value at continuous voxel coordinates (voxel centres at integers), corners
    outside the grid counting as 0; ``volume`` is indexed [x, y, z], as volume.npy is stored."""
    size_x, size_y, size_z = volume.shape
    ix, iy, iz = math.floor(x), math.floor(y), math.floor(z)
    fx, fy, fz = x - ix, y - iy, z - iz
    if 0 <= ix < size_x - 1 and 0 <= iy < size_y - 1 and 0 <= iz < size_z - 1:
        # Every corner inside: most samples, read without a bounds test per corner.
        return _inside(volume, ix, iy, iz, fx, fy, fz)
    total = 0.0
    for c in range(2):
        k = iz + c
        if k < 0 or k >= size_z:
            continue
        wz = fz if c else 1.0 - fz
        for b in range(2):
            j = iy + b
            if j < 0 or j >= size_y:
                continue
            wyz = wz * (fy if b else 1.0 - fy)
            for a in range(2):
                i = ix + a
                if i < 0 or i >= size_x:
                    continue
                total += wyz * (fx if a else 1.0 - fx) * volume[i, j, k]
    return total


@njit(parallel=PRANGE_ONLY, cache=True)
def sample_cube_into(volume, points, out) -> None:
    """out[i] = ``volume`` read at world point ``points[i]`` of the cube [-1, 1]³, whose faces are
    the outer faces of the edge voxels: falling to 0 over the voxel past the outer voxel centres
    (0 from half a voxel outside the cube on), and 0 at points that are not finite."""
    size_x, size_y, size_z = volume.shape
    for i in prange(points.shape[0]):
        # The voxel coordinate of the face at -1 is -0.5, of the face at +1 size - 0.5.
        x = ((points[i, 0] + 1.0) * size_x - 1.0) * 0.5
        y = ((points[i, 1] + 1.0) * size_y - 1.0) * 0.5
        z = ((points[i, 2] + 1.0) * size_z - 1.0) * 0.5
        # Also false for NaN, and keeps math.floor's integers in range for any huge coordinate.
        if -1.0 < x < size_x and -1.0 < y < size_y and -1.0 < z < size_z:
            out[i] = trilinear(volume, x, y, z)
        else:
            out[i] = 0.0


@njit(parallel=PRANGE_ONLY, cache=True)
def sample_cube_gradient_into(volume, points, out) -> None:
    """out[i] = the gradient of ``volume`` (values per world unit) at world point ``points[i]`` of
    the cube [-1, 1]³ read as :func:`sample_cube_into` reads it: along each axis the difference of
    the two reads one voxel either side, over two voxels' width (inside the grid, the trilinear
    read of the central differences at the voxel centres). 0 at points that are not finite."""
    size_x, size_y, size_z = volume.shape
    for i in prange(points.shape[0]):
        x = ((points[i, 0] + 1.0) * size_x - 1.0) * 0.5
        y = ((points[i, 1] + 1.0) * size_y - 1.0) * 0.5
        z = ((points[i, 2] + 1.0) * size_z - 1.0) * 0.5
        out[i, 0], out[i, 1], out[i, 2] = 0.0, 0.0, 0.0
        # A read past -2 or size + 1 voxels is 0 on both sides; the bounds also keep NaN out.
        if not (-2.0 < x < size_x + 1.0 and -2.0 < y < size_y + 1.0 and -2.0 < z < size_z + 1.0):
            continue
        # Two voxels are 4 / size world units: a difference over them times size / 4.
        out[i, 0] = (_read(volume, x + 1.0, y, z) - _read(volume, x - 1.0, y, z)) * (0.25 * size_x)
        out[i, 1] = (_read(volume, x, y + 1.0, z) - _read(volume, x, y - 1.0, z)) * (0.25 * size_y)
        out[i, 2] = (_read(volume, x, y, z + 1.0) - _read(volume, x, y, z - 1.0)) * (0.25 * size_z)


@njit(inline="always")
def _read(volume, x, y, z):
    """``trilinear`` where it has a corner inside the grid, else 0, as ``sample_cube_into`` reads.
    Inside, the eight corners are read inline; near the faces ``_read_at_faces`` is called: six
    inlined copies of the whole of ``trilinear`` took LLVM 24–28 s to compile, and six calls of
    it made the read 2.5 times slower."""
    size_x, size_y, size_z = volume.shape
    ix, iy, iz = math.floor(x), math.floor(y), math.floor(z)
    if 0 <= ix < size_x - 1 and 0 <= iy < size_y - 1 and 0 <= iz < size_z - 1:
        return _inside(volume, ix, iy, iz, x - ix, y - iy, z - iz)
    return _read_at_faces(volume, x, y, z)


@njit(cache=True)
def _read_at_faces(volume, x, y, z):
    size_x, size_y, size_z = volume.shape
    if -1.0 < x < size_x and -1.0 < y < size_y and -1.0 < z < size_z:
        return trilinear(volume, x, y, z)
    return 0.0
