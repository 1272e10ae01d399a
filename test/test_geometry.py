import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from equidiff_core import geometry as g

CENTER = np.array([0.45, -0.1, 0.18])

angles = st.floats(-2 * math.pi, 2 * math.pi, allow_nan=False)
seeds = st.integers(0, 2**32 - 1)


def random_poses(seed: int, n: int = 5) -> np.ndarray:
    rng = np.random.default_rng(seed)
    R = Rotation.random(n, random_state=seed).as_matrix()
    return g.make_pose(R, rng.uniform(-1, 1, (n, 3)))


@settings(max_examples=50, deadline=None)
@given(seeds)
def test_action_round_trip(seed):
    T = random_poses(seed)
    width = np.random.default_rng(seed).uniform(0, 0.08, len(T))
    a = g.pose_to_action(T, width)
    assert a.shape == (len(T), 10)
    T2, w2 = g.action_to_pose(a)
    np.testing.assert_allclose(T2, T, atol=1e-9)
    np.testing.assert_allclose(w2, width)


def test_rot6d_is_first_two_rows_and_decodes_by_gram_schmidt():
    R = Rotation.from_euler("xyz", [0.3, -0.2, 1.1]).as_matrix()
    d6 = g.rot6d_from_matrix(R)
    np.testing.assert_allclose(d6, np.concatenate([R[0], R[1]]))
    noisy = d6 + np.array([0.01, -0.02, 0.0, 0.03, 0.0, -0.01])
    R2 = g.matrix_from_rot6d(noisy)
    np.testing.assert_allclose(R2 @ R2.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R2) == pytest.approx(1.0)
    np.testing.assert_allclose(R2[0], noisy[:3] / np.linalg.norm(noisy[:3]))


def test_torch_and_numpy_agree_batched():
    T = random_poses(3, 7).reshape(7, 4, 4)
    w = np.linspace(0, 0.08, 7)
    a_np = g.pose_to_action(T, w)
    a_t = g.pose_to_action(torch.as_tensor(T), torch.as_tensor(w))
    assert isinstance(a_t, torch.Tensor)
    np.testing.assert_allclose(a_t.numpy(), a_np)
    rot_np = g.rotate_action(a_np, 0.7, CENTER)
    rot_t = g.rotate_action(a_t, 0.7, CENTER)
    np.testing.assert_allclose(rot_t.numpy(), rot_np, atol=1e-12)
    T_t, _ = g.action_to_pose(a_t.reshape(1, 7, 10))
    assert T_t.shape == (1, 7, 4, 4)


@settings(max_examples=50, deadline=None)
@given(angles, angles, seeds)
def test_group_law(t1, t2, seed):
    a = g.pose_to_action(random_poses(seed), np.full(5, 0.04))
    composed = g.rotate_action(g.rotate_action(a, t2, CENTER), t1, CENTER)
    np.testing.assert_allclose(composed, g.rotate_action(a, t1 + t2, CENTER), atol=1e-9)
    np.testing.assert_allclose(g.rotate_action(a, 0.0, CENTER), a, atol=1e-12)


@settings(max_examples=50, deadline=None)
@given(angles, seeds)
def test_rotating_pose_then_encoding_equals_encoding_then_rotating(theta, seed):
    T = random_poses(seed)
    w = np.full(5, 0.02)
    lhs = g.pose_to_action(g.rotate_pose(T, theta, CENTER), w)
    rhs = g.rotate_action(g.pose_to_action(T, w), theta, CENTER)
    np.testing.assert_allclose(lhs, rhs, atol=1e-9)


def test_action_rep_is_the_papers_irreps():
    theta = 0.9
    rep = g.action_rep(theta)
    r1 = g.rho1(theta)
    for i, j in ((0, 1), (3, 6), (4, 7), (5, 8)):
        np.testing.assert_allclose(rep[np.ix_([i, j], [i, j])], r1)
    for k in (2, 9):  # z and width are invariant
        assert rep[k, k] == 1 and np.count_nonzero(rep[k]) == 1


@settings(max_examples=30, deadline=None)
@given(angles)
def test_relative_rotation_change_of_basis_block_diagonalises(theta):
    rho = g.relative_rotation_rep(theta)
    # rho is the conjugation action on row-major flattened rotations
    Rr = Rotation.random(random_state=1).as_matrix()
    np.testing.assert_allclose(rho @ Rr.reshape(9), (g.rotz(theta) @ Rr @ g.rotz(theta).T).reshape(9), atol=1e-12)
    P = g.P_REL_ROT
    blocks = P @ rho @ np.linalg.inv(P)
    np.testing.assert_allclose(blocks, g.irrep_block_diag(theta, g.REL_ROT_IRREPS), atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(angles)
def test_relative_pose_change_of_basis_block_diagonalises(theta):
    rho = g.relative_pose_rep(theta)
    A = random_poses(2, 1)[0]
    np.testing.assert_allclose(rho @ A.reshape(16), g.rotate_relative_pose(A, theta).reshape(16), atol=1e-12)
    blocks = g.P_REL_POSE @ rho @ np.linalg.inv(g.P_REL_POSE)
    np.testing.assert_allclose(blocks, g.irrep_block_diag(theta, g.REL_POSE_IRREPS), atol=1e-9)


def test_relative_action_commutes_with_absolute_rotation():
    # T_{t+1} = A T_t: rotating the whole scene rotates A by conjugation.
    T_t, A = random_poses(5, 2)
    theta = 1.3
    Tg = g.rotz_pose(theta)
    np.testing.assert_allclose(g.rotate_relative_pose(A, theta) @ (Tg @ T_t), Tg @ (A @ T_t), atol=1e-12)


@pytest.mark.parametrize("k", [1, 2, 3, -1])
def test_voxel_rotation_by_quarter_turns_moves_points_with_actions(k):
    res, edge = 8, 0.4
    size = edge / res
    lower = CENTER - edge / 2
    grid = np.zeros((4, res, res, res), dtype=np.uint8)
    idx = np.array([6, 1, 3])
    grid[:, idx[0], idx[1], idx[2]] = [255, 10, 20, 30]
    theta = k * math.pi / 2
    rotated = g.rotate_voxel_grid(grid, theta)
    point = lower + (idx + 0.5) * size
    a = np.zeros(10)
    a[:3] = point
    a[3:9] = [1, 0, 0, 0, 1, 0]
    moved = g.rotate_action(a, theta, CENTER)[:3]
    new_idx = np.floor((moved - lower) / size).astype(int)
    assert rotated[0].sum() == 255
    np.testing.assert_array_equal(rotated[:, new_idx[0], new_idx[1], new_idx[2]], [255, 10, 20, 30])
    # torch path gives the same
    np.testing.assert_array_equal(g.rotate_voxel_grid(torch.as_tensor(grid), theta).numpy(), rotated)


@pytest.mark.parametrize("mode", ["nearest", "trilinear"])
def test_resampled_rotation_matches_exact_quarter_turn(mode):
    rng = np.random.default_rng(0)
    grid = rng.random((2, 16, 16, 5)).astype(np.float32)
    exact = g.rotate_voxel_grid(grid, math.pi / 2)
    resampled = g._resample_rotated(grid, math.pi / 2, mode)
    np.testing.assert_allclose(resampled, exact, atol=1e-4)


def test_arbitrary_angle_rotation_moves_a_blob_like_its_pose():
    res = 32
    grid = np.zeros((1, res, res, 4), dtype=np.float32)
    grid[0, 24:27, 15:18, 1] = 1.0  # blob centred at index (25, 16)
    theta = math.radians(30)
    out = g.rotate_voxel_grid(grid, theta, mode="trilinear")
    c = (res - 1) / 2
    xs, ys = np.meshgrid(np.arange(res), np.arange(res), indexing="ij")
    w = out[0, :, :, 1]
    centroid = np.array([(w * xs).sum(), (w * ys).sum()]) / w.sum()
    expected = g.rho1(theta) @ (np.array([25.0, 16.0]) - c) + c
    np.testing.assert_allclose(centroid, expected, atol=0.3)
    assert out[0, :, :, [0, 2, 3]].sum() == 0  # z untouched


@pytest.mark.parametrize(
    "bad, message",
    [
        (np.diag([1.0, 1.0, -1.0]), "reflection"),
        (np.eye(3) * 1.1, "orthonormal"),
        (np.full((3, 3), np.nan), "NaN"),
        (np.eye(2), "shape"),
    ],
)
def test_invalid_rotations_are_rejected(bad, message):
    with pytest.raises(g.GeometryError, match=message):
        g.validate_rotation(bad)


def test_invalid_actions_and_poses_are_rejected():
    a = np.zeros(10)
    a[3:9] = [1, 0, 0, 0, 1, 0]
    a[0] = np.nan
    with pytest.raises(g.GeometryError, match="NaN"):
        g.action_to_pose(a)
    with pytest.raises(g.GeometryError, match="parallel"):
        g.matrix_from_rot6d(np.array([1, 0, 0, 2, 0, 0.0]))
    T = np.eye(4)
    T[3, 0] = 1
    with pytest.raises(g.GeometryError, match="last row"):
        g.pose_to_action(T, np.array(0.0))
    with pytest.raises(g.GeometryError, match="unit length"):
        g.pose_from_pos_quat([0, 0, 0], [0, 0, 0, 2])


def test_quaternion_helpers_round_trip():
    T = random_poses(11, 3)
    p, q = g.pos_quat_from_pose(T)
    np.testing.assert_allclose(g.pose_from_pos_quat(p, q), T, atol=1e-12)


@pytest.mark.parametrize("theta", [0.3, math.pi / 4, -1.9, 2.5, math.pi / 2 + 1e-3])
def test_nearest_rotation_picks_the_voxels_slice_resampling_picks(theta):
    # The gather of whole columns must reproduce grid_sample's nearest choice on every slice exactly (the
    # way it was computed before), including its rounding at pixel boundaries and the empty corners, for
    # the training grids' shape and dtype and for float grids.
    rng = np.random.default_rng(1)
    occupied = rng.random((2, 1, 1, 64, 64, 64)) < 0.05
    grid = torch.from_numpy((rng.integers(1, 256, (2, 1, 4, 64, 64, 64)) * occupied).astype(np.uint8))
    values = torch.from_numpy(rng.standard_normal((3, 12, 12, 7)).astype(np.float32))
    with g.slice_resampled_rotation():
        resampled = g.rotate_voxel_grid(grid, theta), g.rotate_voxel_grid(values, theta)
    rotated = g.rotate_voxel_grid(grid, theta)
    assert rotated.dtype == torch.uint8 and rotated.shape == grid.shape
    assert rotated.any() and not torch.equal(rotated, grid)
    assert torch.equal(rotated, resampled[0])
    assert torch.equal(g.rotate_voxel_grid(values, theta), resampled[1])
    np.testing.assert_array_equal(g.rotate_voxel_grid(values.numpy(), theta), resampled[1].numpy())
