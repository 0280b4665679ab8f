"""Timestamped pose trajectories and the TUM text format (``timestamp tx ty tz qx qy qz qw``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from .errors import DatasetError
from .geometry import quat_to_rot, rot_to_quat


@dataclass
class Trajectory:
    """Poses (N, 4, 4), camera-to-world, at strictly increasing timestamps (N,) in seconds."""

    stamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.stamps = np.asarray(self.stamps, dtype=np.float64).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.stamps) != len(self.poses):
            raise ValueError(f"{len(self.stamps)} timestamps but {len(self.poses)} poses")

    def __len__(self) -> int:
        return len(self.stamps)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]

    def subset(self, idx: np.ndarray | list[int]) -> Trajectory:
        idx = np.asarray(idx, dtype=int)
        return Trajectory(self.stamps[idx], self.poses[idx])

    def transformed(self, left: np.ndarray | None = None, right: np.ndarray | None = None) -> Trajectory:
        """``left @ pose @ right`` for every pose: a world change on the left, a sensor extrinsic on the right."""
        poses = self.poses
        if left is not None:
            poses = np.einsum("ij,njk->nik", left, poses)
        if right is not None:
            poses = np.einsum("nij,jk->nik", poses, right)
        return Trajectory(self.stamps.copy(), poses)

    @classmethod
    def from_tum_array(cls, data: np.ndarray) -> Trajectory:
        data = np.asarray(data, dtype=np.float64).reshape(-1, 8)
        poses = np.tile(np.eye(4), (len(data), 1, 1))
        poses[:, :3, :3] = quat_to_rot(data[:, 4:8])
        poses[:, :3, 3] = data[:, 1:4]
        return cls(data[:, 0], poses)

    def to_tum_array(self) -> np.ndarray:
        out = np.empty((len(self), 8))
        out[:, 0] = self.stamps
        out[:, 1:4] = self.positions
        out[:, 4:8] = rot_to_quat(self.poses[:, :3, :3]) if len(self) else np.empty((0, 4))
        return out


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file; comments (#) and blank lines are skipped; commas are accepted."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"trajectory file not found: {path}")
    return parse_tum(path.read_text(), str(path))


def parse_tum(text: str, where: str = "trajectory") -> Trajectory:
    """A TUM trajectory from its text (a file's, or an HTTP reply's), ordered by stamp; :class:`DatasetError` names
    ``where`` and the line for anything that is not ``timestamp tx ty tz qx qy qz qw``."""
    rows = []
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        if len(fields) != 8:
            raise DatasetError(f"{where}:{lineno}: expected 'timestamp tx ty tz qx qy qz qw', got {len(fields)}")
        try:
            row = [float(f) for f in fields]
        except ValueError as exc:
            raise DatasetError(f"{where}:{lineno}: {exc}") from None
        if not np.isfinite(row).all():
            raise DatasetError(f"{where}:{lineno}: a value is not a finite number: {line!r}")
        if np.linalg.norm(row[4:]) < 1e-9:
            raise DatasetError(f"{where}:{lineno}: the quaternion qx qy qz qw is zero, not a rotation")
        rows.append(row)
    if not rows:
        raise DatasetError(f"trajectory file has no poses: {where}")
    data = np.array(rows)
    order = np.argsort(data[:, 0], kind="stable")
    return Trajectory.from_tum_array(data[order])


def write_tum(path: str | Path, trajectory: Trajectory, header: str | None = None) -> None:
    """Write a trajectory in TUM format with full float precision."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text((f"# {header}\n" if header else "") + tum_text(trajectory))


def tum_text(trajectory: Trajectory) -> str:
    """The TUM text of a trajectory (as written by :func:`write_tum`)."""
    rows = [f"{r[0]:.6f} " + " ".join(f"{v:.9f}" for v in r[1:]) for r in trajectory.to_tum_array()]
    return "# timestamp tx ty tz qx qy qz qw\n" + "".join(line + "\n" for line in rows)


def interpolate_poses(trajectory: Trajectory, stamps: np.ndarray,
                      max_gap: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Poses (N, 4, 4) interpolated at ``stamps`` (linear translation, slerp rotation) and a validity mask.

    A stamp is valid when it lies between two trajectory poses at most ``max_gap`` seconds apart.
    Ground truth and camera run at similar rates but not in sync, and 20 ms of hand-held rotation
    is several pixels, so taking the nearest pose is not good enough for a 3 px criterion.
    """
    stamps = np.asarray(stamps, dtype=np.float64).reshape(-1)
    times = trajectory.stamps
    upper = np.clip(np.searchsorted(times, stamps, side="left"), 1, max(len(times) - 1, 1))
    lower = upper - 1
    poses = np.tile(np.eye(4), (len(stamps), 1, 1))
    if len(times) < 2:
        return poses, np.zeros(len(stamps), bool)
    span = times[upper] - times[lower]
    valid = (stamps >= times[lower]) & (stamps <= times[upper]) & (span <= max_gap) & (span > 0)
    alpha = np.where(valid, (stamps - times[lower]) / np.where(span > 0, span, 1.0), 0.0)
    # slerp on each stamp's own pair of poses: r0 exp(alpha log(r0^-1 r1)), the formula of scipy's Slerp, which
    # takes one list of keys instead (and no repeated stamp)
    r0 = Rotation.from_matrix(trajectory.poses[lower, :3, :3])
    r1 = Rotation.from_matrix(trajectory.poses[upper, :3, :3])
    poses[:, :3, :3] = (r0 * Rotation.from_rotvec(alpha[:, None] * (r0.inv() * r1).as_rotvec())).as_matrix()
    t0, t1 = trajectory.poses[lower, :3, 3], trajectory.poses[upper, :3, 3]
    poses[:, :3, 3] = (1 - alpha[:, None]) * t0 + alpha[:, None] * t1
    return poses, valid


def smooth_trajectory(trajectory: Trajectory, acceleration: float, angular_acceleration: float,
                      max_gap_s: float = 0.2) -> Trajectory:
    """The trajectory smoothed under a white-noise acceleration model (a fixed-interval smoother).

    Positions ``p`` minimise ``sum |p_i - m_i|^2 / s_n^2 + sum |a_i|^2 / s_a^2`` where ``m`` are the measured
    positions and ``a_i`` the finite-difference acceleration at pose ``i``; rotations likewise on their
    quaternions, renormalised. Both scales come from the trajectory itself: its second differences split into
    a part that varies slowly (the camera's acceleration, averaged over 9 poses) and the rest (frame noise,
    which flips sign from pose to pose). ``s_n`` is the robust spread of the rest (white noise has 6 times its
    variance there), ``s_a`` the RMS of the slow part, but at least ``acceleration`` (m/s^2;
    ``angular_acceleration`` rad/s^2 for rotation). So a steady estimate, or a camera that really
    accelerates, is smoothed less. Runs of poses further apart than ``max_gap_s`` (dropped or skipped frames)
    are smoothed separately; runs of fewer than 8 poses are left as they are.
    """
    out = trajectory.poses.copy()
    breaks = np.flatnonzero(np.diff(trajectory.stamps) > max_gap_s) + 1
    for run in np.split(np.arange(len(trajectory)), breaks):
        if len(run) < 8:
            continue
        stamps, poses = trajectory.stamps[run], trajectory.poses[run]
        quaternions = rot_to_quat(poses[:, :3, :3])
        flips = np.cumsum(np.r_[False, np.sum(quaternions[1:] * quaternions[:-1], axis=1) < 0]) % 2 == 1
        quaternions[flips] *= -1  # one hemisphere, so that neighbours are close in R^4
        out[run, :3, 3] = _smooth_series(stamps, poses[:, :3, 3], acceleration)
        smoothed = _smooth_series(stamps, quaternions, angular_acceleration / 2)  # |dq/dt| = |omega| / 2
        out[run, :3, :3] = quat_to_rot(smoothed / np.linalg.norm(smoothed, axis=1, keepdims=True))
    return Trajectory(trajectory.stamps.copy(), out)


def _smooth_series(stamps: np.ndarray, values: np.ndarray, min_acceleration: float) -> np.ndarray:
    """Least-squares smoothing of ``values`` (N, D) at ``stamps`` (N,): see :func:`smooth_trajectory`."""
    # imported here: only the end of a run needs scipy, and services import this module for the pose format
    from scipy.ndimage import uniform_filter1d
    from scipy.sparse import csr_matrix, diags
    from scipy.sparse.linalg import spsolve

    second = np.diff(values, n=2, axis=0)
    # the camera's own acceleration varies slowly; frame noise flips sign from frame to frame
    motion = uniform_filter1d(second, size=9, axis=0, mode="nearest")
    noise_var = (1.4826 * float(np.median(np.abs(second - motion)))) ** 2 / 6.0
    if noise_var <= 1e-18:
        return values
    dt = float(np.median(np.diff(stamps)))
    acceleration_var = max(float(np.mean(motion**2)) / dt**4, min_acceleration**2)
    h = np.diff(stamps)
    h1, h2 = h[:-1], h[1:]
    scale = 2.0 / (h1 + h2)
    count = len(stamps)
    rows = np.arange(count - 2)  # row i: the acceleration at pose i + 1 from poses i, i + 1, i + 2
    data = np.concatenate([scale / h1, -scale * (1 / h1 + 1 / h2), scale / h2])
    cols = np.concatenate([rows, rows + 1, rows + 2])
    accelerations = csr_matrix((data, (np.tile(rows, 3), cols)), shape=(count - 2, count))
    system = diags(np.full(count, 1.0 / noise_var)) + (accelerations.T @ accelerations) / acceleration_var
    return np.column_stack([spsolve(system.tocsc(), values[:, d] / noise_var) for d in range(values.shape[1])])
