import nibabel as nib
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.volume.orientation import axis_codes, reorient_to_ras


def _random_orthogonal_affine(permutation, signs, spacing, origin):
    affine = np.zeros((4, 4))
    for axis, target in enumerate(permutation):
        affine[target, axis] = signs[axis] * spacing[axis]
    affine[:3, 3] = origin
    affine[3, 3] = 1
    return affine


@given(
    permutation=st.permutations([0, 1, 2]),
    signs=st.tuples(*[st.sampled_from([-1, 1])] * 3),
    spacing=st.tuples(*[st.floats(0.1, 10)] * 3),
    origin=st.tuples(*[st.floats(-500, 500)] * 3),
)
@settings(max_examples=100, deadline=None)
def test_matches_nibabel_canonical(permutation, signs, spacing, origin):
    affine = _random_orthogonal_affine(permutation, signs, spacing, origin)
    data = np.arange(3 * 4 * 5, dtype=np.float32).reshape(3, 4, 5)
    canonical = nib.as_closest_canonical(nib.Nifti1Image(data, affine))
    ras_data, ras_affine = reorient_to_ras(data, affine)
    assert axis_codes(ras_affine) == "RAS"
    assert np.array_equal(ras_data, canonical.get_fdata().astype(np.float32))
    assert np.allclose(ras_affine, canonical.affine)


def test_lps_scan_keeps_voxel_positions():
    affine = np.diag([-0.7, -0.7, 5.0, 1.0])
    affine[:3, 3] = (150, 300, -700)
    data = np.random.default_rng(0).normal(size=(6, 5, 4)).astype(np.float32)
    ras_data, ras_affine = reorient_to_ras(data, affine)
    assert axis_codes(affine) == "LPS"
    # Voxel (1, 2, 3) of the LPS array is voxel (4, 2, 3) of the RAS one, at the same place.
    assert ras_data[6 - 1 - 1, 5 - 1 - 2, 3] == data[1, 2, 3]
    assert np.allclose(affine @ [1, 2, 3, 1], ras_affine @ [4, 2, 3, 1])
