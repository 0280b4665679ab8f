import numpy as np

from twohr.geometry import invert_pose, make_pose, nearest_rotation, quat_to_rot, rot_to_quat, so3_exp, umeyama


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
