import re

import numpy as np
import pytest

from reloc_service.core import geometry as g
from reloc_service.core.errors import GeometryError


def random_pose(rng):
    return g.se3_exp(np.concatenate([rng.normal(size=3), rng.normal(size=3)]))


def test_quaternion_round_trip_and_convention():
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[3] >= 0 else -q
        assert np.allclose(g.matrix_to_quat_xyzw(g.quat_xyzw_to_matrix(q)), q, atol=1e-12)
    # Hamilton x y z w: 90 deg about z maps x to y.
    q_z90 = [0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)]
    assert np.allclose(g.quat_xyzw_to_matrix(q_z90) @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_compose_invert_transform():
    rng = np.random.default_rng(1)
    a_from_b, b_from_c = random_pose(rng), random_pose(rng)
    points_c = rng.normal(size=(10, 3))
    a_from_c = g.compose(a_from_b, b_from_c)
    assert np.allclose(g.transform_points(a_from_c, points_c),
                       g.transform_points(a_from_b, g.transform_points(b_from_c, points_c)))
    assert np.allclose(g.compose(a_from_b, g.invert(a_from_b)), np.eye(4), atol=1e-12)


def test_exp_log_round_trip():
    rng = np.random.default_rng(2)
    for _ in range(50):
        xi = np.concatenate([rng.normal(size=3), rng.uniform(-3, 3, size=3) / np.sqrt(3)])
        assert np.allclose(g.se3_log(g.se3_exp(xi)), xi, atol=1e-9)
    assert np.allclose(g.se3_exp(np.zeros(6)), np.eye(4))


def test_pose_error():
    rng = np.random.default_rng(3)
    pose = random_pose(rng)
    delta = g.se3_exp([0.1, 0.0, 0.0, 0.0, 0.0, np.deg2rad(5)])
    dt, dr = g.pose_error(pose @ delta, pose)
    assert dr == pytest.approx(np.deg2rad(5), abs=1e-9)
    assert dt == pytest.approx(np.linalg.norm((pose @ delta)[:3, 3] - pose[:3, 3]))


def test_tum_round_trip():
    rng = np.random.default_rng(4)
    pose = random_pose(rng)
    assert np.allclose(g.pose_from_tum(g.pose_to_tum(pose)), pose, atol=1e-12)


@pytest.mark.parametrize("bad, match", [
    (np.eye(3), "expected a \\(4, 4\\)"),
    (np.full((4, 4), np.nan), "non-finite"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "not a proper rotation"),
    (np.diag([2.0, 1.0, 1.0, 1.0]), "not a proper rotation"),
    (np.vstack([np.eye(4)[:3], [0, 0, 1, 1]]), "last row"),
])
def test_check_pose_rejects(bad, match):
    with pytest.raises(GeometryError, match=match):
        g.check_pose(bad)


def test_quaternion_rejects_non_unit_and_nan():
    with pytest.raises(GeometryError):
        g.quat_xyzw_to_matrix([0, 0, 0, 2.0])
    with pytest.raises(GeometryError):
        g.quat_xyzw_to_matrix([0, 0, np.nan, 1.0])


def test_look_at_axes():
    world_from_cam = g.look_at([0, 0, 1], [2, 0, 1], up=[0, 0, 1])
    # camera z (forward) along world +x, camera y (down) along world -z
    assert np.allclose(world_from_cam[:3, 2], [1, 0, 0])
    assert np.allclose(world_from_cam[:3, 1], [0, 0, -1])
    g.check_pose(world_from_cam)


def test_quaternion_round_trip_through_the_one_implementation():
    from reloc_client.protocol import quat_xyzw_to_rotation, rotation_to_quat_xyzw_array
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    q = rng.normal(size=(500, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    # 180-degree turns (w = 0) and the identity exercise every branch of Shepperd's method.
    q = np.vstack([q, np.eye(4)[[0, 1, 2, 3]], [[0.5, 0.5, 0.5, 0.5]]])
    q[q[:, 3] < 0] *= -1
    rotations = quat_xyzw_to_rotation(q)
    assert rotations.shape == (len(q), 3, 3)
    np.testing.assert_allclose(rotations, Rotation.from_quat(q).as_matrix(), atol=1e-12)
    back = rotation_to_quat_xyzw_array(rotations)
    same_sign = np.where((back * q).sum(axis=1, keepdims=True) < 0, -back, back)
    np.testing.assert_allclose(same_sign, q, atol=1e-12)
    assert np.all(back[:, 3] >= 0)
    for qi, ri in zip(q[:20], rotations[:20], strict=True):
        np.testing.assert_allclose(g.quat_xyzw_to_matrix(qi), ri, atol=1e-15)
        np.testing.assert_allclose(g.matrix_to_quat_xyzw(ri), back[len(back) - len(q)
                                   + list(map(tuple, q)).index(tuple(qi))], atol=1e-15)


def test_so3_exp_is_scipys_rotation_to_the_bit():
    """so3_exp calls SciPy's compiled rotation functions directly where SciPy has them: the
    values of ``Rotation.from_rotvec(v).as_matrix()``, at every scale of angle (SciPy's
    small-angle series included), and a (1, 3) vector still goes through Rotation."""
    from scipy.spatial.transform import Rotation

    from reloc_service.core import geometry

    assert geometry._rotation_kernels is not None  # the SciPy the project installs has them
    rng = np.random.default_rng(11)
    for scale in (0.0, 1e-9, 1e-5, 1e-3, 0.1, 1.0, 3.0):
        for v in rng.normal(size=(2000, 3)) * scale:
            assert np.array_equal(geometry.so3_exp(v), Rotation.from_rotvec(v).as_matrix())
    batch = geometry.so3_exp(np.array([[0.1, 0.2, 0.3]]))
    assert batch.shape == (1, 3, 3)


def test_se3_exp_many_rotations_are_scipys_rotation_to_the_bit():
    """se3_exp_many's rotations are ``Rotation.from_rotvec(omega).as_matrix()``'s values (it
    calls the same compiled functions), at every scale of angle, for one twist or many;
    none gives an empty batch."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(12)
    for scale in (0.0, 1e-9, 1e-5, 1e-3, 0.1, 1.0, 3.0):
        for n in (1, 7, 500):
            twists = rng.normal(size=(n, 6)) * scale
            poses = g.se3_exp_many(twists)
            assert np.array_equal(poses[:, :3, :3],
                                  Rotation.from_rotvec(twists[:, 3:]).as_matrix())
            np.testing.assert_allclose(poses, np.stack([g.se3_exp(x) for x in twists]),
                                       rtol=0, atol=1e-12)
    assert g.se3_exp_many(np.zeros((0, 6))).shape == (0, 4, 4)


def test_se3_adjoint_moves_a_twist_across_a_pose():
    """``a_from_b @ exp(xi) @ b_from_a == exp(Ad(a_from_b) xi)``, for one pose and a stack."""
    rng = np.random.default_rng(5)
    poses = [g.se3_exp(rng.normal(size=6)) for _ in range(4)]
    for a_from_b in poses:
        xi = rng.normal(size=6) * 0.3
        np.testing.assert_allclose(a_from_b @ g.se3_exp(xi) @ g.invert(a_from_b),
                                   g.se3_exp(g.se3_adjoint(a_from_b) @ xi), atol=1e-12)
    stacked = g.se3_adjoints(np.stack(poses))
    for a_from_b, adjoint in zip(poses, stacked, strict=True):
        np.testing.assert_array_equal(adjoint, g.se3_adjoint(a_from_b))


def test_check_pose_covariance_says_what_is_wrong():
    good = np.diag([1e-4, 1e-4, 1e-4, 1e-6, 1e-6, 1e-6])
    good[0, 3] = good[3, 0] = 5e-6
    np.testing.assert_array_equal(g.check_pose_covariance(good), good)
    g.check_pose_covariance(np.zeros((6, 6)))     # exact: allowed
    nearly = good.copy()
    nearly[0, 3] *= 1 + 1e-12                   # float noise of a product is not asymmetry
    assert np.array_equal(g.check_pose_covariance(nearly), g.check_pose_covariance(nearly).T)
    for bad, says in ((np.eye(3), "shape (3, 3)"), (np.full((6, 6), np.nan), "NaN"),
                      (good + np.triu(np.full((6, 6), 1e-5), 1), "not symmetric"),
                      (np.diag([1.0, 1, 1, 1, 1, -1e-3]), "positive semi-definite")):
        with pytest.raises(GeometryError, match=re.escape(says)):
            g.check_pose_covariance(bad, name="kf 3")
