"""The skeleton's bones and the KCS bone matrix C (Wandt & Rosenhahn 2019, Eq. 3-6)."""

from __future__ import annotations

import numpy as np

from repnet.core import skeleton
from tests.training.conftest import STANDING


def test_each_bone_matrix_column_is_a_bone_vector_child_minus_parent() -> None:
    c = skeleton.bone_matrix()
    assert c.shape == (skeleton.NUM_JOINTS, skeleton.NUM_BONES)
    assert np.all(c.sum(axis=0) == 0) and np.all((c != 0).sum(axis=0) == 2)  # one +1, one -1 (Eq. 4)
    bones = STANDING.T @ c  # B = X C, (3, B) (Eq. 5-6)
    for b, (parent, child) in enumerate(skeleton.BONES):
        np.testing.assert_allclose(bones[:, b], STANDING[child] - STANDING[parent])  # Eq. 3


def test_every_non_root_joint_ends_one_bone_and_mirroring_twice_is_the_identity() -> None:
    assert sorted(child for _, child in skeleton.BONES) == [j for j in range(skeleton.NUM_JOINTS) if j != 0]
    assert all(skeleton.PARENTS[child] == parent for parent, child in skeleton.BONES)
    assert [skeleton.MIRROR[j] for j in skeleton.MIRROR] == list(range(skeleton.NUM_JOINTS))
