"""Engine coordinate conventions: quaternion rule == matrix rule, handedness and axes as documented."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.rotations import matrix_from_quat, quat_multiply, quat_rotate, random_quat
from mocapd.protocols.conventions import CONVENTIONS, MVN, UNITY, UNREAL, convention


@pytest.mark.parametrize("name", sorted(CONVENTIONS))
def test_quaternion_rule_matches_matrix_rule(name: str) -> None:
    c = convention(name)
    q = random_quat(np.random.default_rng(3), (50,))
    np.testing.assert_allclose(matrix_from_quat(c.quaternions(q)), c.matrices(matrix_from_quat(q)), atol=1e-12)


@pytest.mark.parametrize("name", sorted(CONVENTIONS))
def test_rotating_then_converting_equals_converting_then_rotating(name: str) -> None:
    c = convention(name)
    rng = np.random.default_rng(4)
    q = random_quat(rng, (20,))
    v = rng.normal(size=(20, 3))
    np.testing.assert_allclose(c.directions(quat_rotate(q, v)), quat_rotate(c.quaternions(q), c.directions(v)),
                               atol=1e-12)  # fmt: skip
    # Composition is preserved, so local rotations down a chain convert bone by bone.
    a, b = q[:10], q[10:]
    np.testing.assert_allclose(c.quaternions(quat_multiply(a, b)), quat_multiply(c.quaternions(a), c.quaternions(b)),
                               atol=1e-12)  # fmt: skip


def test_axes_as_documented() -> None:
    left, up, forward = np.eye(3)  # mocapd: +X is the subject's left, +Y up, +Z forward (rest pose)
    np.testing.assert_allclose(UNITY.positions(left), [-1, 0, 0])  # Unity +X is right
    np.testing.assert_allclose(UNREAL.positions(forward), [100, 0, 0])  # Unreal +X forward, centimetres
    np.testing.assert_allclose(UNREAL.positions(up), [0, 0, 100])
    np.testing.assert_allclose(UNREAL.positions(left), [0, -100, 0])  # Unreal +Y is right
    np.testing.assert_allclose(MVN.positions(left), [0, 1, 0])  # MVN: X forward, Y left, Z up
    assert UNITY.left_handed and UNREAL.left_handed and not MVN.left_handed


def test_unknown_name_lists_choices() -> None:
    with pytest.raises(KeyError, match="unity"):
        convention("blender")
