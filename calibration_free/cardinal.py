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
        `DIRECTIONS` order.
    """
    east = goals[None, :, 0] - points[:, None, 0]  # the goal's offset, (n_points, n_goals)
    north = goals[None, :, 1] - points[:, None, 1]
    # The bearing in quarter turns, u in [-2, 2]; a direction's raw score
    # 1 - |wrap(theta - theta_c)| / (pi / 2) is then 1 - |u - u_c| for up, down and right
    # (where the wrap matters the score is negative either way) and |u| - 1 for left.
    # Exact at the reference angles: arctan2 returns pi / 2 and pi exactly.
    quarter_turns = np.arctan2(north, east) / (np.pi / 2)
    magnitude = np.abs(quarter_turns)
    raw = np.empty((*quarter_turns.shape, len(DIRECTIONS)))
    np.subtract(1.0, np.abs(quarter_turns - 1.0), out=raw[..., 0])  # up
    np.subtract(1.0, np.abs(quarter_turns + 1.0), out=raw[..., 1])  # down
    np.subtract(1.0, magnitude, out=raw[..., 2])  # right
    np.subtract(magnitude, 1.0, out=raw[..., 3])  # left
    np.maximum(raw, 0.0, out=raw)  # sums to 1 over the directions
    zero = raw <= 0.0
    n_zero = zero[..., 0].astype(float)
    for k in range(1, len(DIRECTIONS)):  # elementwise: numpy's short-axis sums are slow
        n_zero += zero[..., k]
    noisy = raw
    noisy *= 1.0 - alpha
    noisy += zero * (alpha / np.maximum(n_zero, 1.0))[..., None]
    noisy[(east == 0.0) & (north == 0.0)] = 1.0 / len(DIRECTIONS)  # at the goal
    return noisy
