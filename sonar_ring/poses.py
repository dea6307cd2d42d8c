"""2-D poses: composition, relative poses, and a robot's odometry history to place pings at their stamps.

A pose is ``(x, y, yaw)`` of a frame in its parent frame, m and rad (REP 103).
:class:`PoseHistory` is the one pose policy of the mapper node and of
``sonar-ring process``: a ping is placed at the robot's pose at its stamp,
interpolated between the odometry messages around it.
"""

from __future__ import annotations

import bisect
import math

import numpy as np


def compose(pose, step) -> np.ndarray:
    """``pose`` moved by ``step`` given in its own frame: the pose of ``step``'s frame in ``pose``'s parent, (3,)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array([pose[0] + c * step[0] - s * step[1], pose[1] + s * step[0] + c * step[1], pose[2] + step[2]])


def pose_covariance_at(pose, covariance, step) -> np.ndarray:
    """Covariance (3, 3) of ``compose(pose, step)`` for a ``pose`` with ``covariance`` (3, 3) and an exact ``step``.

    The lever ``R(yaw) step_xy`` turns with the yaw: ``J = [[1, 0, -l_y], [0, 1, l_x], [0, 0, 1]]``.
    """
    c, s = math.cos(pose[2]), math.sin(pose[2])
    lever_x, lever_y = c * step[0] - s * step[1], s * step[0] + c * step[1]
    jacobian = np.array([[1.0, 0.0, -lever_y], [0.0, 1.0, lever_x], [0.0, 0.0, 1.0]])
    return jacobian @ np.asarray(covariance, dtype=float) @ jacobian.T


def turned_pose_covariance(covariance, yaw: float) -> np.ndarray:
    """``R C R^T``: a pose covariance ``C`` (3, 3) of ``(x, y, yaw)`` turned by ``yaw`` (rad), ``R`` turning x and y.

    From a frame into its parent, for a frame at heading ``yaw`` there (``-yaw``: back).
    """
    c, s = math.cos(yaw), math.sin(yaw)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return rotation @ covariance @ rotation.T


def step_covariance(start, start_covariance, end, end_covariance) -> np.ndarray | None:
    """Covariance (3, 3) of the step from ``start`` to ``end`` in ``start``'s frame, of the two poses' covariances.

    ``start``, ``end``: poses ``(x, y, yaw)`` in one frame with their covariances (3, 3) in it.  Odometry
    integrated step by step (wheel odometry, an EKF's prediction) grows its covariance so:
    ``C_end = J C_start J^T + R C_step R^T`` (``J C_start J^T``: :func:`pose_covariance_at`; ``R`` the start's
    rotation), hence ``C_step = R^T (C_end - J C_start J^T) R``.  None when that is not positive definite: a
    covariance that does not grow so (a fixed one, all zeros for unknown) says nothing of the step.
    """
    growth = np.asarray(end_covariance, dtype=float) - pose_covariance_at(start, start_covariance,
                                                                          relative_pose(start, end))
    step = turned_pose_covariance(0.5 * (growth + growth.T), -start[2])
    if not np.all(np.isfinite(step)) or np.linalg.eigvalsh(step)[0] <= 0.0:
        return None
    return step


def relative_pose(start, end) -> tuple[float, float, float]:
    """``end`` in the frame of ``start`` (both in one frame): forward, sideways (m) and turn (rad, wrapped)."""
    c, s = math.cos(start[2]), math.sin(start[2])
    dx, dy = end[0] - start[0], end[1] - start[1]
    turn = math.remainder(end[2] - start[2], 2.0 * math.pi)
    return c * dx + s * dy, -s * dx + c * dy, turn


def inverse(pose) -> np.ndarray:
    """The pose of the parent frame in ``pose``'s frame, (3,)."""
    return np.array(relative_pose(pose, (0.0, 0.0, 0.0)))


def turned_covariances(covariance, rotation) -> np.ndarray:
    """``R C R^T`` for each 2 x 2 covariance of ``covariance`` (L, 2, 2) and the rotation ``R`` (2, 2), (L, 2, 2).

    As two matrix products over all L matrices at once, ``(R C)^T = C^T R^T`` stacked as (2L, 2) rows: the
    same products in the same order as ``R @ C @ R.T`` (the same numbers bit for bit), in half its time (a
    ping's hundred covariances: 10 instead of 19 us; numpy runs a stacked product one matrix at a time).
    """
    count = len(covariance)
    covariance = np.asarray(covariance, dtype=float)
    turned = (np.ascontiguousarray(covariance.transpose(0, 2, 1)).reshape(2 * count, 2) @ rotation.T)  # (R C)^T
    return (np.ascontiguousarray(turned.reshape(count, 2, 2).transpose(0, 2, 1)).reshape(2 * count, 2)
            @ rotation.T).reshape(count, 2, 2)


QUATERNION_NORM_TOLERANCE = 1e-3
"""How far a quaternion's squared norm may be from 1 for :func:`yaw_of` to take it as a rotation; its yaw is then
off by at most about as many radians (a float32 quaternion's round-off is about 1e-7; an unset orientation is all
zeros)."""


def yaw_of(orientation) -> float:
    """Yaw (rotation about z) of a unit quaternion with fields ``x, y, z, w``, rad; NaN when it is not a rotation.

    Not a rotation: a component that is not finite, or a squared norm more than
    :data:`QUATERNION_NORM_TOLERANCE` off 1 -- such a quaternion's yaw would be a number, and wrong.
    """
    x, y, z, w = orientation.x, orientation.y, orientation.z, orientation.w
    # Products, not powers: a huge component makes inf here, where ** raises OverflowError.
    if not abs(x * x + y * y + z * z + w * w - 1.0) <= QUATERNION_NORM_TOLERANCE:  # NaN fails too
        return math.nan
    return float(math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y ** 2 + z ** 2)))


class PoseHistory:
    """Odometry poses and their covariances by stamp, to place a ping at its stamp.

    Parameters
    ----------
    limit : int or None
        Poses kept at least (the oldest go first, in batches); None keeps all (a whole bag).
    """

    def __init__(self, limit: int | None = 500):
        self._limit = limit
        self._stamps: list[int] = []
        self._poses: list[np.ndarray] = []
        self._covariances: list[np.ndarray | None] = []

    def __len__(self) -> int:
        return len(self._stamps)

    def add(self, stamp: int, pose, covariance=None) -> None:
        """Append the pose ``(x, y, yaw)`` stamped ``stamp`` (ns, after the last one's), and its covariance or None."""
        self._stamps.append(stamp)
        self._poses.append(np.asarray(pose, dtype=float))
        self._covariances.append(None if covariance is None else np.asarray(covariance, dtype=float))
        if self._limit is not None and len(self._stamps) >= 2 * self._limit:
            del self._stamps[:-self._limit], self._poses[:-self._limit], self._covariances[:-self._limit]

    def clear(self) -> None:
        """Forget every pose (time jumped back)."""
        self._stamps.clear()
        self._poses.clear()
        self._covariances.clear()

    def too_old(self, stamp: int) -> bool:
        """Whether ``stamp`` (ns) lies before the oldest pose kept."""
        return bool(self._stamps) and stamp < self._stamps[0]

    def at(self, stamp: int) -> np.ndarray | None:
        """The pose at ``stamp`` (ns), interpolated; None while no pose at or after it exists.

        A stamp before the first pose gets the first pose (a ping older than
        the history: check :meth:`too_old` first where that matters).
        """
        around = self._around(stamp)
        if around is None:
            return None
        index, weight = around
        if weight is None:
            return self._poses[index]
        before, after = self._poses[index - 1], self._poses[index]
        turn = math.remainder(after[2] - before[2], 2.0 * math.pi)
        return np.array([*(before[:2] + weight * (after[:2] - before[:2])), before[2] + weight * turn])

    def covariance_at(self, stamp: int) -> np.ndarray | None:
        """The pose's covariance (3, 3) at ``stamp`` (ns), interpolated as :meth:`at`; None where a pose lacks one."""
        around = self._around(stamp)
        if around is None:
            return None
        index, weight = around
        if weight is None:
            return self._covariances[index]
        before, after = self._covariances[index - 1], self._covariances[index]
        if before is None or after is None:
            return None
        return before + weight * (after - before)

    def _around(self, stamp: int) -> tuple[int, float | None] | None:
        """The first pose at or after ``stamp`` and the weight of it against the one before (None: it alone).

        None when there is no such pose.  It alone: at the stamp, or the first pose.
        """
        index = bisect.bisect_left(self._stamps, stamp)
        if index == len(self._stamps):
            return None
        if self._stamps[index] == stamp or index == 0:
            return index, None
        return index, (stamp - self._stamps[index - 1]) / (self._stamps[index] - self._stamps[index - 1])
