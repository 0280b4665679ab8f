import numpy as np
import pytest

from twohr.geometry import (
    huber_loss,
    huber_weights,
    invert_pose,
    make_pose,
    nearest_rotation,
    quat_to_rot,
    rot_to_quat,
    rotation_angle,
    skew,
    so3_exp,
    so3_exp_batch,
    so3_log,
    umeyama,
)
from twohr.pose import depth_residual
from twohr_services.tracker.bundle_adjustment import normal_equations, schur_layout, solve_schur


def random_rotations(n, seed=0):
    rng = np.random.default_rng(seed)
    return np.array([so3_exp(rng.normal(0, 1.0, 3)) for _ in range(n)])


def test_quaternion_round_trip():
    rs = random_rotations(50)
    back = quat_to_rot(rot_to_quat(rs))
    assert np.allclose(back, rs, atol=1e-12)
    q = rot_to_quat(rs)
    assert np.all(q[:, 3] >= 0)
    assert np.allclose(np.linalg.norm(q, axis=1), 1)


def test_known_quaternion():
    # 90 degrees about z
    r = quat_to_rot(np.array([0, 0, np.sqrt(0.5), np.sqrt(0.5)]))
    assert np.allclose(r, [[0, -1, 0], [1, 0, 0], [0, 0, 1]])


def test_invert_pose():
    translations = np.random.default_rng(1).normal(size=(5, 3))
    poses = np.array([make_pose(r, t) for r, t in zip(random_rotations(5), translations, strict=True)])
    assert np.allclose(invert_pose(poses) @ poses, np.eye(4), atol=1e-12)


def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(100, 3))
    r = random_rotations(1, seed=5)[0]
    t = np.array([1.0, -2.0, 0.5])
    dst = 2.5 * src @ r.T + t
    r_est, t_est, s_est = umeyama(src, dst, with_scale=True)
    assert np.allclose(r_est, r) and np.allclose(t_est, t) and np.isclose(s_est, 2.5)
    r_est, t_est, s_est = umeyama(src, src @ r.T + t)
    assert s_est == 1.0 and np.allclose(r_est, r) and np.allclose(t_est, t)


def test_nearest_rotation_removes_scale():
    r = random_rotations(1, seed=9)[0]
    assert np.allclose(nearest_rotation(1.059 * r), r)


def test_skew_is_the_cross_product():
    rng = np.random.default_rng(3)
    v, x = rng.normal(size=(4, 5, 3)), rng.normal(size=(4, 5, 3))
    k = skew(v)
    assert k.shape == (4, 5, 3, 3)
    assert np.allclose((k @ x[..., None])[..., 0], np.cross(v, x), atol=1e-14)
    assert np.array_equal(k, -np.swapaxes(k, -1, -2))


def test_so3_exp_batch_and_log_round_trip():
    rng = np.random.default_rng(4)
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    omegas = axes * rng.uniform(0, np.pi - 1e-3, (200, 1))
    rotations = so3_exp_batch(omegas)
    assert np.allclose(rotations @ np.swapaxes(rotations, 1, 2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(rotations), 1.0, atol=1e-12)
    assert np.allclose(rotation_angle(rotations), np.linalg.norm(omegas, axis=1), atol=1e-7)
    assert np.allclose(rotations, [so3_exp(w) for w in omegas], atol=1e-12)
    assert np.allclose([so3_log(r) for r in rotations], omegas, atol=1e-9)
    assert np.allclose(so3_exp_batch(omegas.reshape(20, 10, 3)), rotations.reshape(20, 10, 3, 3), atol=0)
    tiny = np.array([1e-10, -2e-10, 3e-10])  # the small-angle branch: I + skew(w)
    assert np.allclose(so3_exp_batch(tiny), np.eye(3) + skew(tiny), atol=1e-20)
    assert np.array_equal(so3_exp_batch(np.zeros(3)), np.eye(3))


def test_huber_loss_and_weights():
    r = np.array([-5.0, -2.0, -0.5, 0.0, 0.3, 2.0, 7.0])
    assert np.allclose(huber_loss(r, 2.0), [8.0, 2.0, 0.125, 0.0, 0.045, 2.0, 12.0])
    assert np.allclose(huber_weights(r, 2.0), [0.4, 1.0, 1.0, 1.0, 1.0, 1.0, 2 / 7])
    assert huber_loss(r.reshape(7, 1), 1.0).shape == (7, 1)
    # continuous at the threshold, and the IRLS weight times r is the loss's gradient
    x = np.linspace(-6, 6, 1201)
    for threshold in (0.5, 1.0, 2.0):
        h = 1e-6
        gradient = (huber_loss(x + h, threshold) - huber_loss(x - h, threshold)) / (2 * h)
        assert np.allclose(gradient, huber_weights(x, threshold) * x, atol=1e-6)
        edge = np.array([threshold - 1e-12, threshold + 1e-12])
        assert np.diff(huber_loss(edge, threshold))[0] == pytest.approx(0, abs=1e-11)


def test_depth_residual_is_an_inverse_depth_error_with_its_slope():
    z = np.array([1.0, 2.0, 3.0, 4.0])
    z_meas = np.array([1.1, 0.0, 3.0, 3.5])
    res, slope = depth_residual(1.0 / z, z_meas, 0.05)
    assert np.allclose(res, [(1 - 1 / 1.1) / 0.05, 0.0, 0.0, (1 / 4 - 1 / 3.5) / 0.05])
    h = 1e-7
    above, below = depth_residual(1.0 / (z + h), z_meas, 0.05)[0], depth_residual(1.0 / (z - h), z_meas, 0.05)[0]
    numeric = (above - below) / (2 * h)
    assert np.allclose(slope, numeric, rtol=1e-6) and slope[1] == 0


@pytest.mark.parametrize(("dim", "damping"), [(6, 0.0), (6, 1e-2), (3, 1e-3)])
def test_schur_solver_matches_a_dense_solve_of_the_normal_equations(dim, damping):
    """Each observation touches one pose and one point; fixed poses' observations still weigh on their points."""
    rng = np.random.default_rng(dim + int(1e4 * damping))
    n_poses, n_points, n_obs, rows = 5, 12, 70, 3
    fixed = np.array([True, False, False, True, False])
    obs_pose = np.r_[np.repeat(np.arange(n_poses), 2), rng.integers(0, n_poses, n_obs - 2 * n_poses)]
    obs_point = np.r_[np.arange(n_points), np.arange(n_points), rng.integers(0, n_points, n_obs - 2 * n_points)]
    jac_pose = rng.normal(size=(n_obs, rows, dim))
    jac_point = rng.normal(size=(n_obs, rows, 3))
    res = rng.normal(size=(n_obs, rows))
    weights = rng.uniform(0.2, 1.0, (n_obs, rows))
    slot = np.cumsum(~fixed) - 1
    slot[fixed] = -1
    n_free = int((~fixed).sum())
    layout = schur_layout(slot[obs_pose], obs_point, n_free, n_points)
    steps = solve_schur(normal_equations(layout, jac_pose, jac_point, res, weights), damping)
    assert steps is not None
    step_pose, step_point = steps
    # the full Jacobian over (free poses, points), the damped normal equations, one dense solve
    jac = np.zeros((n_obs * rows, dim * n_free + 3 * n_points))
    for o in range(n_obs):
        if slot[obs_pose[o]] >= 0:
            jac[o * rows:(o + 1) * rows, dim * slot[obs_pose[o]]:dim * (slot[obs_pose[o]] + 1)] = jac_pose[o]
        col = dim * n_free + 3 * obs_point[o]
        jac[o * rows:(o + 1) * rows, col:col + 3] = jac_point[o]
    w = weights.reshape(-1)
    hessian = jac.T @ (jac * w[:, None])
    hessian += np.diag(damping * np.diag(hessian) + 1e-9)
    dense = np.linalg.solve(hessian, -jac.T @ (w * res.reshape(-1)))
    assert step_pose.shape == (n_free, dim) and step_point.shape == (n_points, 3)
    assert np.allclose(step_pose.reshape(-1), dense[:dim * n_free], rtol=1e-9, atol=1e-11)
    assert np.allclose(step_point.reshape(-1), dense[dim * n_free:], rtol=1e-9, atol=1e-11)


def test_rotation_helpers_take_batches_and_agree():
    """so3_log takes (..., 3, 3) as so3_exp_batch takes (..., 3), up to 180 degrees; so3_exp is the same map;
    quaternions are (x, y, z, w) with w >= 0; a zero quaternion or a NaN matrix gives NaN, not an exception."""
    rng = np.random.default_rng(5)
    axes = rng.normal(size=(4, 6, 3))
    omegas = axes / np.linalg.norm(axes, axis=-1, keepdims=True) * rng.uniform(0, np.pi - 1e-6, (4, 6, 1))
    rotations = so3_exp_batch(omegas)
    assert np.allclose(so3_log(rotations), omegas, atol=1e-9)
    assert np.array_equal(so3_exp(omegas[1, 2]), rotations[1, 2])
    q = rot_to_quat(rotations)
    assert q.shape == (4, 6, 4) and np.all(q[..., 3] >= 0)
    assert np.allclose(q[..., :3] / np.sin(np.linalg.norm(omegas, axis=-1, keepdims=True) / 2),
                       omegas / np.linalg.norm(omegas, axis=-1, keepdims=True))
    assert np.allclose(quat_to_rot(q), rotations, atol=1e-12)
    half_turn = rot_to_quat(quat_to_rot([0.0, 0.6, 0.8, 0.0]))
    assert np.allclose(np.abs(half_turn), [0.0, 0.6, 0.8, 0.0])
    with np.errstate(invalid="ignore", divide="ignore"):
        assert np.isnan(quat_to_rot(np.array([[0.0, 0, 0, 0], [0, 0, 0, 1]]))[0]).all()
        assert np.isnan(rot_to_quat(np.full((3, 3), np.nan))).all()
