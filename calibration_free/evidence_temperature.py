"""Calibrating the matching evidence once a target has confirmed the labels.

The matching filter adds ``log m`` per signal, ``m`` the match of the label a task expects
against the decoder's confusion-corrected prediction, tempered by the user error rate eps
(method.md §3). Tempered, one signal's evidence is weaker than the decoder can support:
the pairwise threshold is then the thesis's guard against wrong targets. Once a target has
confirmed the history's labels, the learner can measure how strong the evidence really is:
the temperature ``tau`` that makes ``softmax(tau log m)`` over the classes calibrated
class probabilities of the adopted labels (maximum likelihood over the history's
out-of-fold predictions). The evidence of the next task segment is then ``tau log m`` per
signal, a Bayesian filter's log-likelihood with the decoder the adopted labels trained,
and the decision a posterior threshold over all tasks (the normalised likelihood), which
holds whatever the number of close competitors.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.special import log_softmax

#: The temperatures searched, (lowest, highest).
TEMPERATURE_BOUNDS = (0.05, 20.0)


def fit_temperature(log_matches: np.ndarray, label_weights: np.ndarray) -> float:
    """The temperature that makes ``softmax(tau log m)`` the likeliest class probabilities.

    Parameters
    ----------
    log_matches : ndarray, shape (n_signals, K)
        `label_log_matches` of the signals.
    label_weights : ndarray, shape (n_signals, K)
        The labels (one-hot, or soft weights) the probabilities must explain.

    Returns
    -------
    float
        ``argmax_tau sum_i sum_c w_ic log softmax(tau log m_i)_c`` within
        `TEMPERATURE_BOUNDS` (bounded scalar search; the objective is concave in tau).
    """
    if log_matches.shape != label_weights.shape:
        raise ValueError(
            f"log matches {log_matches.shape} and label weights {label_weights.shape} differ"
        )

    def loss(tau: float) -> float:
        return -float(np.sum(label_weights * log_softmax(tau * log_matches, axis=1)))

    low, high = TEMPERATURE_BOUNDS
    return float(minimize_scalar(loss, bounds=(low, high), method="bounded").x)
