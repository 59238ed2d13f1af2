"""The cardinal-direction guidance frame of a goal point in the plane (method-extensions §3).

A teacher at position ``x`` who wants the goal ``g`` names the cardinal direction of the
goal's bearing ``theta = atan2(g_y - x_y, g_x - x_x)``: direction ``c`` (reference angle
``theta_c``) gets the raw score ``max(0, 1 - |wrap(theta - theta_c)| / (pi / 2))``. The raw
scores sum to 1, and only the two directions adjacent to the bearing are non-zero. The
noise ``alpha`` then keeps ``1 - alpha`` of the mass on the non-zero entries and spreads
``alpha`` evenly over the zero ones (the thesis code's ``apply_noise``); at the goal itself
(``g == x``) every direction is equally likely.
"""

from __future__ import annotations

import numpy as np

#: The frame's labels, in class order.
DIRECTIONS: tuple[str, ...] = ("up", "down", "right", "left")
#: Reference angle of each direction, radians (north, south, east, west).
REFERENCE_ANGLES = np.array([np.pi / 2, -np.pi / 2, 0.0, np.pi])


def cardinal_guidance(points: np.ndarray, goals: np.ndarray, alpha: float) -> np.ndarray:
    """Label distributions of the cardinal frame.

    Parameters
    ----------
    points : ndarray, shape (n_points, 2)
        Teacher positions in the plane.
    goals : ndarray, shape (n_goals, 2)
        Goal hypotheses.
    alpha : float
        Noise, in [0, 1).

    Returns
    -------
    ndarray, shape (n_points, n_goals, 4)
        ``p(direction | point, goal)``, each row summing to 1, directions in
        :data:`DIRECTIONS` order.
    """
    offset = goals[None, :, :] - points[:, None, :]
    bearing = np.arctan2(offset[..., 1], offset[..., 0])  # [-pi, pi]
    gap = np.abs(bearing[..., None] - REFERENCE_ANGLES)  # [0, 2 pi]
    np.minimum(gap, 2 * np.pi - gap, out=gap)  # |wrap(theta - theta_c)|, in [0, pi]
    gap *= -2 / np.pi
    gap += 1.0
    raw = np.maximum(gap, 0.0, out=gap)  # sums to 1 over the directions
    zero = raw <= 0.0
    n_zero = zero[..., 0].astype(float)
    for k in range(1, len(DIRECTIONS)):  # elementwise: numpy's short-axis sums are slow
        n_zero += zero[..., k]
    noisy = raw
    noisy *= 1.0 - alpha
    noisy += zero * (alpha / np.maximum(n_zero, 1.0))[..., None]
    noisy[(offset[..., 0] == 0.0) & (offset[..., 1] == 0.0)] = 1.0 / len(DIRECTIONS)  # at the goal
    return noisy
