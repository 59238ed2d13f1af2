"""Scatters kept as an earlier eigendecomposition plus the signals added since."""

import numpy as np
import pytest

from decoding.scatter_eigen import RollingScatterEigen, refresh_period


@pytest.mark.parametrize("period", [1, 3, 8])
def test_every_set_is_its_decomposition_plus_its_pending_signals(period):
    """After every signal, ``V diag(e) V^T + Y^T Y`` is each set's scatter, ``V`` stays
    orthonormal, and no set holds ``period`` or more pending signals."""
    rng = np.random.default_rng(period)
    n_sets, d = 5, 6
    eigen = RollingScatterEigen(n_sets, d, period)
    scatters = np.zeros((n_sets, d, d))
    for _ in range(40):
        signal = rng.normal(size=d)
        members = rng.random(n_sets) < 0.8
        scatters[members] += np.outer(signal, signal)
        eigen.add(signal, members, scatters)
        now = eigen.current()
        assert now.pending.shape[-2] < period
        rebuilt = (now.basis * now.eigenvalues[:, None, :]) @ np.swapaxes(now.basis, 1, 2)
        rebuilt += np.swapaxes(now.pending, 1, 2) @ now.pending
        np.testing.assert_allclose(rebuilt, scatters, atol=1e-10)
        np.testing.assert_allclose(
            np.swapaxes(now.basis, 1, 2) @ now.basis, np.broadcast_to(np.eye(d), now.basis.shape),
            atol=1e-12,
        )


def test_the_decompositions_follow_the_signals_not_the_reads():
    """Two copies fed the same signals, one read after every signal and one never, hold
    the same numbers."""
    rng = np.random.default_rng(1)
    signals = rng.normal(size=(30, 4))
    read, unread = RollingScatterEigen(3, 4, 4), RollingScatterEigen(3, 4, 4)
    scatters = np.zeros((3, 4, 4))
    for signal in signals:
        scatters += np.outer(signal, signal)
        for eigen in (read, unread):
            eigen.add(signal, np.ones(3, bool), scatters)
        read.current()
    first, second = read.current(), unread.current()
    for field in ("basis", "eigenvalues", "pending"):
        np.testing.assert_array_equal(getattr(first, field), getattr(second, field))


def test_the_period_shrinks_as_the_tasks_grow():
    assert refresh_period(25, 57) == 8
    assert refresh_period(400, 57) == 4
    assert refresh_period(2500, 57) == 2
    assert refresh_period(2500, 20) == 1
    assert refresh_period(1, 200) == 8
    with pytest.raises(ValueError, match="period must be >= 1"):
        RollingScatterEigen(2, 3, 0)
