"""A seeded K-class Gaussian signal generator of a given nominal balanced accuracy.

The thesis's artificial datasets (method-extensions §7.2, §7.3, ch. 5): each class ``k`` is
an isotropic unit Gaussian in ``D`` dimensions around a mean ``delta * v_k``, where the
``v_k`` are equally spaced unit directions (a regular simplex in ``K - 1`` dimensions when
``D >= K - 1``, points on the unit circle in the plane otherwise). The spacing ``delta`` is
chosen so that the *Bayes-optimal* classifier (known means, equal priors) has the requested
balanced accuracy; a decoder learned from few signals does worse. The accuracy of a given
``delta`` is measured by Monte Carlo with a fixed internal seed and bisected, so the mapping
from accuracy to ``delta`` is deterministic.

With a ``mixing_decay`` gamma > 0 the signals are then seen through a fixed linear mixing,
as EEG features are through volume conduction and a shared reference: ``x -> A x`` with
``A = U diag(sqrt(lambda)) V^T`` (``U``, ``V`` random rotations drawn from a fixed seed for
the dimension, ``lambda_j`` proportional to ``j^-gamma``, mean 1). The noise becomes
correlated with a decaying spectrum, and the class differences, rotated by ``V`` off the
axes, spread over all its directions, the weak ones included. A linear map changes no
Bayes-optimal accuracy, so the nominal accuracy holds; a covariance shrunk towards the
identity, which cannot undo the mixing, loses some of it (gamma = 0: a plain rotation,
which changes nothing for such a decoder either).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from acquisition.labelled import LabelledFeatures
from decoding.validation import check_range

#: Monte Carlo signals per class when measuring the accuracy of a spacing.
_CALIBRATION_SIGNALS = 20_000
_CALIBRATION_SEED = 20141
#: Seed of the mixing's rotations (one mixing per dimension and decay, whatever the session).
_MIXING_SEED = 20142


def class_directions(n_classes: int, n_dims: int) -> np.ndarray:
    """Equally spaced unit directions of the class means.

    Returns
    -------
    ndarray, shape (n_classes, n_dims)
        A regular simplex centred on 0 (``n_dims >= n_classes - 1``), or ``n_classes``
        equally spaced points on the unit circle of the first two axes.
    """
    if n_classes < 2 or n_dims < 1 or (n_dims == 1 and n_classes > 2):
        raise ValueError(
            f"a Gaussian dataset needs 2+ classes and enough dimensions; got {n_classes} "
            f"classes in {n_dims} dimension(s) (1-D holds only 2 classes)"
        )
    directions = np.zeros((n_classes, n_dims))
    if n_dims >= n_classes - 1:
        simplex = np.eye(n_classes) - 1.0 / n_classes  # centred, in the K-dim space
        basis = np.linalg.svd(simplex)[2][: n_classes - 1]  # its (K-1)-dim span
        points = simplex @ basis.T
        directions[:, : n_classes - 1] = points / np.linalg.norm(points, axis=1, keepdims=True)
    else:
        angles = 2 * np.pi * np.arange(n_classes) / n_classes
        directions[:, 0], directions[:, 1] = np.cos(angles), np.sin(angles)
    return directions


def _bayes_accuracy(delta: float, directions: np.ndarray) -> float:
    rng = np.random.default_rng(_CALIBRATION_SEED)
    means = delta * directions
    correct = 0
    for k, mean in enumerate(means):
        x = mean + rng.standard_normal((_CALIBRATION_SIGNALS, directions.shape[1]))
        distances = ((x[:, None, :] - means[None]) ** 2).sum(axis=2)
        correct += int((distances.argmin(axis=1) == k).sum())
    return correct / (_CALIBRATION_SIGNALS * len(means))


@lru_cache(maxsize=64)
def class_spacing(accuracy: float, n_classes: int, n_dims: int) -> float:
    """The spacing ``delta`` at which the Bayes-optimal balanced accuracy is ``accuracy``
    (bisection to 1e-3 in ``delta``)."""
    check_range("accuracy", accuracy, 1.0 / n_classes + 0.01, 0.999)
    directions = class_directions(n_classes, n_dims)
    low, high = 0.0, 20.0
    while high - low > 1e-3:
        middle = (low + high) / 2
        low, high = (middle, high) if _bayes_accuracy(middle, directions) < accuracy else (
            low, middle
        )
    return (low + high) / 2


def mixing_matrix(n_dims: int, decay: float) -> np.ndarray:
    """The fixed linear mixing ``A`` (n_dims, n_dims) of ``decay`` gamma (module docstring):
    eigenvalues of ``A A^T`` proportional to ``j^-gamma``, mean 1."""
    check_range("mixing decay", decay, 0.0, 10.0)
    rng = np.random.default_rng([_MIXING_SEED, n_dims])
    rotations = [np.linalg.qr(rng.standard_normal((n_dims, n_dims)))[0] for _ in range(2)]
    spectrum = np.arange(1, n_dims + 1, dtype=float) ** -decay
    spectrum /= spectrum.mean()
    return (rotations[0] * np.sqrt(spectrum)) @ rotations[1].T


def generate_gaussian_features(
    n_per_class: int,
    n_classes: int,
    n_dims: int,
    accuracy: float,
    seed: int | np.random.Generator,
    mixing_decay: float = 0.0,
) -> LabelledFeatures:
    """``n_per_class`` signals of each class, class by class.

    Parameters
    ----------
    n_per_class : int
    n_classes : int
        Classes (labels 0..n_classes-1).
    n_dims : int
        Dimensions of a signal.
    accuracy : float
        Nominal (Bayes-optimal) balanced accuracy, in (1/n_classes, 1).
    seed : int or Generator
        Draws the signals (standard normal noise, class by class).
    mixing_decay : float, default 0
        gamma of the fixed linear mixing (module docstring); 0: none.

    Returns
    -------
    LabelledFeatures
        ``features`` shape (n_per_class * n_classes, n_dims), arbitrary units.
    """
    rng = np.random.default_rng(seed)
    means = class_spacing(accuracy, n_classes, n_dims) * class_directions(n_classes, n_dims)
    labels = np.repeat(np.arange(n_classes), n_per_class)
    features = means[labels] + rng.standard_normal((labels.size, n_dims))
    mixed = ""
    if mixing_decay:
        features = features @ mixing_matrix(n_dims, mixing_decay).T
        mixed = f", mixed with decay {mixing_decay:g}"
    return LabelledFeatures(
        features=features,
        labels=labels,
        n_classes=n_classes,
        source=f"gaussian (nominal balanced accuracy {accuracy:g}, {n_dims}-D{mixed})",
    )
