"""Seeded synthetic ErrP EEG: labelled correct / error epochs of tunable difficulty.

Model of one epoch (microvolts, channels on the 10-10 system):

- background EEG: a 1/f^chi spectrum (chi = 1.5) drawn with random phases in the
  frequency domain, spatially correlated by the square root of an exponential covariance
  exp(-distance / 4) between electrodes (distances in 10 % steps of the 10-20 system), plus
  a posterior alpha rhythm (about 10 Hz, varying per trial in frequency and amplitude);
  about 10 µV RMS at fronto-central sites;
- a response to every action (a visual P1/N1 to the cursor move), equal for both classes;
- the outcome response, Gaussian waves in time with per-trial latency and amplitude jitter
  and a fronto-central topography (method.md section 8): after errors a negativity at
  250 ms, a positivity at 400 ms and a later negativity at 550 ms; after correct actions a
  smaller positivity at 300 ms and a small negativity at 480 ms. Its amplitude is scaled
  by ``gain`` (at gain 1 the error waves peak at -6, +8 and -5 µV at FCz/Cz);
- after errors only, a burst of frontal-midline theta (6 Hz) with random phase: more
  power in error epochs without any change to their mean.

Error epochs carry more power: the mean squared norm of their ErrPFeatures vector is about
1.3 times that of correct epochs at accuracy 0.6, 1.5 at 0.78 and 2.3 at 0.97 (see the
calibration tool's output).

No class information lies in a constant offset: both classes share the background, and the
outcome responses are brief waves. `generate_errp_epochs` chooses ``gain`` from the
wanted difficulty, expressed as the balanced accuracy of a shrinkage LDA on
`ErrPFeatures` (see ``_CALIBRATION_ACCURACY``).

Day-to-day drift (`ResponseDrift`, off by default): a user's responses on another
day are scaled in amplitude and shifted in latency. A drift multiplies the outcome responses
(error and correct waves, and the error's theta burst) by ``amplitude`` and delays them by
``latency`` seconds, on top of the per-trial jitter; the background and the response to
every action are unchanged, and every random draw is the same as without it (the same seed
gives the same background, jitters and labels). Without a drift the output is that of the
generator before drift existed, bit for bit.
"""

from __future__ import annotations

import math
import operator
import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import scipy.fft

from acquisition.labelled import LabelledEpochs
from decoding.validation import check_range

SeedLike = int | np.random.SeedSequence | np.random.Generator


@dataclass(frozen=True)
class ResponseDrift:
    """A day's drift of a user's outcome responses (see the module docstring).

    Attributes
    ----------
    amplitude : float, default 1
        Factor of the outcome responses' amplitude (> 0; 1: unchanged).
    latency : float, default 0
        Delay of the outcome responses, s (negative: earlier; 0: unchanged).
    """

    amplitude: float = 1.0
    latency: float = 0.0

    def __post_init__(self) -> None:
        check_range("drift amplitude", float(self.amplitude), 0.0, math.inf, inclusive=False)
        check_range("drift latency", float(self.latency), -0.2, 0.2)

    def then(self, other: ResponseDrift) -> ResponseDrift:
        """This drift followed by ``other``: amplitudes multiply, latencies add."""
        return ResponseDrift(self.amplitude * other.amplitude, self.latency + other.latency)

    def describe(self) -> str:
        """E.g. ``amplitude x0.8, latency +20 ms``."""
        return f"amplitude x{self.amplitude:g}, latency {1000 * self.latency:+g} ms"


#: No drift: the generator's responses as they are.
NO_DRIFT = ResponseDrift()

# ---------------------------------------------------------------------------------------
# Scalp geometry.
# Electrode positions on a flat map in units of 10 % of the nasion-inion distance:
# y from the Cz row (F = 2, FC = 1, C = 0, P = -2 ...), x from the midline (z = 0, odd
# numbers left, even right, 1/2 -> 1, 3/4 -> 2, ...).
_ROWS = {
    "FP": 4.0,
    "AF": 3.0,
    "F": 2.0,
    "FC": 1.0,
    "FT": 1.0,
    "C": 0.0,
    "T": 0.0,
    "CP": -1.0,
    "TP": -1.0,
    "P": -2.0,
    "PO": -3.0,
    "O": -4.0,
    "I": -5.0,
}
_CHANNEL_PATTERN = re.compile(r"^(FP|AF|FC|FT|CP|TP|PO|F|C|T|P|O|I)(Z|\d{1,2})$")
# Centres of the topographies (x, y) and their spatial spread (same units).
_FCZ = (0.0, 1.0)
_CZ = (0.0, 0.0)
_OZ = (0.0, -4.0)
_TOPOGRAPHY_SPREAD = 2.5
_ALPHA_SPREAD = 3.5
# Spatial correlation length of the background EEG.
_CORRELATION_LENGTH = 4.0

# ---------------------------------------------------------------------------------------
# Background EEG.
_ONE_OVER_F_EXPONENT = 1.5
_ONE_OVER_F_KNEE_HZ = 0.5
_BACKGROUND_RMS_UV = 10.0
_ALPHA_FREQUENCY_HZ = (10.0, 0.7)  # mean and across-trial SD
_ALPHA_BANDWIDTH_HZ = 1.0
_ALPHA_RMS_UV = 5.0  # at the alpha centre, before the per-trial amplitude factor
_ALPHA_AMPLITUDE_SD = 0.5  # SD of the log amplitude factor across trials


# ---------------------------------------------------------------------------------------
# Evoked responses: Gaussian waves amplitude * exp(-(t - latency)^2 / (2 width^2)).
class _Wave(NamedTuple):
    amplitude: float  # µV at the topography centre
    latency: float  # s after onset
    width: float  # s (SD of the Gaussian)
    centre: tuple[float, float]  # topography centre (x, y)


_ACTION_RESPONSE = (
    _Wave(3.0, 0.10, 0.02, _OZ),
    _Wave(-4.0, 0.17, 0.025, _OZ),
)
_ERROR_RESPONSE = (
    _Wave(-6.0, 0.25, 0.035, _FCZ),
    _Wave(8.0, 0.40, 0.05, _CZ),
    _Wave(-5.0, 0.55, 0.05, _FCZ),
)
_CORRECT_RESPONSE = (
    _Wave(5.0, 0.30, 0.06, _CZ),
    _Wave(-3.0, 0.48, 0.06, _FCZ),
)
_LATENCY_JITTER_S = 0.02  # SD of the per-trial shift of the outcome response
_AMPLITUDE_JITTER = 0.25  # SD of the log amplitude factor of the outcome response
# Induced frontal-midline theta after errors.
_THETA_FREQUENCY_HZ = 6.0
_THETA_LATENCY_S = 0.35
_THETA_WIDTH_S = 0.12
_THETA_AMPLITUDE_UV = 8.0  # mean peak amplitude at FCz (Rayleigh distributed)


# ---------------------------------------------------------------------------------------
# Difficulty calibration: mean balanced accuracy (10-fold stratified CV of
# LinearDiscriminantAnalysis(solver="lsqr", shrinkage=0.5, priors=[0.5, 0.5]) on default
# ErrPFeatures, 800 correct + 200 error epochs, seeds 0..39) at each gain. Produced by
# `.venv/bin/python tools/calibrate_synthetic.py --seeds 40`; rerun it after changing
# any constant above or the feature extraction.
_CALIBRATION_GAIN = (
    0.0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.2, 1.4, 1.6, 1.8, 2.0,
    2.2, 2.4, 2.6, 2.8, 3.0, 3.2, 3.4, 3.6, 3.8, 4.0,
)  # fmt: skip
_CALIBRATION_ACCURACY = (
    0.5041, 0.5572, 0.6319, 0.6958, 0.7529, 0.7997, 0.8392, 0.8692, 0.8944, 0.9130, 0.9301,
    0.9421, 0.9515, 0.9595, 0.9658, 0.9706, 0.9748, 0.9783, 0.9806, 0.9829, 0.9851,
)  # fmt: skip
#: Range of nominal accuracies accepted by `generate_errp_epochs`.
ACCURACY_RANGE = (0.55, 0.97)


def generate_errp_epochs(
    n_correct: int,
    n_error: int,
    *,
    accuracy: float = 0.78,
    seed: SeedLike = 0,
    sfreq: float = 256.0,
    tmin: float = -0.2,
    tmax: float = 1.0,
    ch_names: Sequence[str] = ("Fz", "FCz", "Cz", "Pz"),
    drift: ResponseDrift = NO_DRIFT,
) -> LabelledEpochs:
    """Synthetic ErrP epochs whose difficulty is a nominal decoding accuracy.

    ``accuracy`` is mapped to the amplitude of the outcome responses through a calibration
    table (piecewise-linear, monotonic interpolation): it is the mean balanced accuracy a
    shrinkage LDA (``LinearDiscriminantAnalysis(solver="lsqr", shrinkage=0.5,
    priors=[0.5, 0.5])``) reaches with 10-fold stratified cross-validation on the default
    `ErrPFeatures` of 800 correct and 200 error epochs at 256 Hz.
    Smaller sets give lower cross-validated accuracies (less training data), larger ones
    higher; the response amplitudes assume the default channels' positions but other
    10-10 channels are accepted.

    Parameters
    ----------
    n_correct, n_error : int
        Numbers of epochs after correct (label 0) and wrong (label 1) actions.
    accuracy : float, default 0.78
        Nominal balanced accuracy, in ``ACCURACY_RANGE`` = [0.55, 0.97].
    seed : int, SeedSequence or Generator, default 0
        Seed of `numpy.random.default_rng`; the same seed gives the same epochs.
    sfreq : float, default 256.0
        Sampling frequency in Hz.
    tmin, tmax : float, default -0.2 and 1.0
        Epoch limits relative to the action onset, in s, rounded to the nearest sample
        (as MNE does) so that the onset falls on a sample.
    ch_names : sequence of str, default ("Fz", "FCz", "Cz", "Pz")
        Channels, 10-10 system names (e.g. "Fz", "FC1", "CPz", "T7"; case-insensitive).
    drift : ResponseDrift, default none
        The day's drift of the outcome responses (applied after ``accuracy`` has chosen
        the gain: a drift of amplitude changes the difficulty).

    Returns
    -------
    LabelledEpochs
        ``epochs`` of shape (n_correct + n_error, n_channels, n_times), float64, µV, in
        random order; ``labels`` 0 = correct, 1 = error; ``tmin`` the time of the first
        sample (-51 / 256 s by default) and ``n_times = round(tmax * sfreq) -
        round(tmin * sfreq) + 1`` (308 by default).

    Examples
    --------
    >>> data = generate_errp_epochs(80, 20, accuracy=0.8, seed=1)
    >>> data.epochs.shape, int(data.labels.sum())
    ((100, 4, 308), 20)
    """
    check_range("accuracy", float(accuracy), *ACCURACY_RANGE)
    gain = float(np.interp(accuracy, _CALIBRATION_ACCURACY, _CALIBRATION_GAIN))
    data = generate_errp_epochs_at_gain(
        n_correct,
        n_error,
        gain=gain,
        seed=seed,
        sfreq=sfreq,
        tmin=tmin,
        tmax=tmax,
        ch_names=ch_names,
        drift=drift,
    )
    drifted = "" if drift == NO_DRIFT else f", drift {drift.describe()}"
    source = f"synthetic ErrP epochs (accuracy={accuracy:.3f}, seed={_describe(seed)}{drifted})"
    return replace(data, source=source)


def generate_errp_epochs_at_gain(
    n_correct: int,
    n_error: int,
    *,
    gain: float,
    seed: SeedLike = 0,
    sfreq: float = 256.0,
    tmin: float = -0.2,
    tmax: float = 1.0,
    ch_names: Sequence[str] = ("Fz", "FCz", "Cz", "Pz"),
    drift: ResponseDrift = NO_DRIFT,
) -> LabelledEpochs:
    """Synthetic ErrP epochs whose outcome responses are scaled by ``gain``.

    The building block of `generate_errp_epochs`, which picks ``gain`` from a wanted
    accuracy. With a given seed every random draw is independent of ``gain``: the same
    seed at two gains gives the same background, jitters and labels.

    ``gain`` (>= 0) scales the outcome responses (0 makes the classes differ only by the
    induced theta power); ``drift`` scales them again and delays them; the other parameters
    and the result are those of `generate_errp_epochs`.
    """
    n_correct = _check_count("n_correct", n_correct)
    n_error = _check_count("n_error", n_error)
    n_epochs = n_correct + n_error
    if n_epochs == 0:
        raise ValueError("n_correct + n_error must be at least 1; got 0 epochs")
    check_range("gain", float(gain), 0.0, math.inf)
    sfreq = check_range("sfreq", float(sfreq), 0.0, math.inf, inclusive=False)
    first, last = round(tmin * sfreq), round(tmax * sfreq)
    if last <= first:
        raise ValueError(f"tmax ({tmax} s) must be after tmin ({tmin} s) by at least a sample")
    times = np.arange(first, last + 1) / sfreq
    positions = _positions(ch_names)
    rng = np.random.default_rng(seed)

    labels = rng.permutation(np.repeat([0, 1], [n_correct, n_error]))
    epochs = _background(rng, n_epochs, positions, len(times), sfreq)
    epochs += _evoked(rng, _ACTION_RESPONSE, np.ones(n_epochs), positions, times)
    is_error = labels == 1
    # A drift's factor 1 and delay 0 change no number: the outcome times are ``times``.
    outcome_times = times - drift.latency
    outcome_gain = gain * drift.amplitude
    epochs += _evoked(rng, _ERROR_RESPONSE, outcome_gain * is_error, positions, outcome_times)
    epochs += _evoked(rng, _CORRECT_RESPONSE, outcome_gain * ~is_error, positions, outcome_times)
    epochs += drift.amplitude * _theta_burst(rng, is_error, positions, outcome_times)
    return LabelledEpochs(
        epochs=epochs,
        sfreq=sfreq,
        tmin=first / sfreq,
        ch_names=tuple(ch_names),
        labels=labels,
        n_classes=2,
        source=f"synthetic ErrP epochs (gain={gain:.4g}, seed={_describe(seed)}"
        + ("" if drift == NO_DRIFT else f", drift {drift.describe()}") + ")",
    )


def _check_count(name: str, value: int) -> int:
    """``value`` as a non-negative int, else a readable error."""
    try:
        count = operator.index(value)
    except TypeError:
        raise TypeError(f"{name} must be an integer; got {value!r}") from None
    if count < 0:
        raise ValueError(f"{name} must be >= 0; got {count}")
    return count


def _describe(seed: SeedLike) -> str:
    """A short description of a seed for the ``source`` field."""
    if isinstance(seed, np.random.SeedSequence):
        return f"SeedSequence(entropy={seed.entropy}, spawn_key={seed.spawn_key})"
    if isinstance(seed, np.random.Generator):
        return "caller's Generator"
    return repr(seed)


def _positions(ch_names: Sequence[str]) -> np.ndarray:
    """Flat scalp positions of channels, shape (n_channels, 2), in 10 % steps."""
    if isinstance(ch_names, str) or len(ch_names) == 0:
        raise ValueError(f"ch_names must be a non-empty sequence of names; got {ch_names!r}")
    if len(set(ch_names)) != len(ch_names):
        raise ValueError(f"ch_names holds duplicate names: {tuple(ch_names)}")
    positions = []
    for name in ch_names:
        match = _CHANNEL_PATTERN.match(str(name).upper())
        if match is None:
            raise ValueError(
                f"unknown channel {name!r}: expected a 10-10 system name such as "
                "'Fz', 'FC1', 'Cz', 'CP2', 'T7', 'Oz'"
            )
        row, column = match.groups()
        number = 0 if column == "Z" else int(column)
        side = -1.0 if number % 2 else 1.0
        positions.append((side * ((number + 1) // 2), _ROWS[row]))
    return np.array(positions)


def _topography(positions: np.ndarray, centre: tuple[float, float], spread: float) -> np.ndarray:
    """Gaussian weight (1 at ``centre``) of each channel, shape (n_channels,)."""
    distance2 = np.sum((positions - np.asarray(centre)) ** 2, axis=1)
    return np.exp(-distance2 / (2 * spread**2))


def _random_spectrum(rng: np.random.Generator, shape: np.ndarray, n: int) -> np.ndarray:
    """Gaussian noise of unit variance with spectral amplitude ``shape``, via an inverse FFT.

    ``shape`` (..., n // 2 + 1) gives the relative amplitude of each frequency bin of
    ``np.fft.rfftfreq(n)``; its DC bin must be 0. Returns shape (..., n): each series has
    variance 1 in expectation (each bin k in 1..n/2-1 contributes 4 |A_k|^2 / n^2).
    """
    amplitude = shape * (n / (2 * np.sqrt(np.sum(shape**2, axis=-1, keepdims=True))))
    # Real and imaginary parts, each standard normal, drawn in one go.
    coefficients = rng.standard_normal((*shape.shape, 2)).view(np.complex128)[..., 0]
    return scipy.fft.irfft(coefficients * amplitude, n=n, axis=-1)


def _background(
    rng: np.random.Generator, n_epochs: int, positions: np.ndarray, n_times: int, sfreq: float
) -> np.ndarray:
    """Spatially correlated 1/f background plus alpha, shape (n_epochs, n_channels, n_times)."""
    # Draw twice the epoch length and keep the start, so that the epoch is not periodic.
    n = 2 * n_times
    freqs = np.fft.rfftfreq(n, 1 / sfreq)
    pink = (freqs**2 + _ONE_OVER_F_KNEE_HZ**2) ** (-_ONE_OVER_F_EXPONENT / 4)
    pink[0] = 0.0
    n_channels = len(positions)
    sources = _random_spectrum(rng, np.broadcast_to(pink, (n_epochs, n_channels, len(freqs))), n)

    distance = np.linalg.norm(positions[:, None, :] - positions[None, :, :], axis=-1)
    eigenvalues, eigenvectors = np.linalg.eigh(np.exp(-distance / _CORRELATION_LENGTH))
    mixing = (eigenvectors * np.sqrt(np.clip(eigenvalues, 0.0, None))) @ eigenvectors.T
    background = _BACKGROUND_RMS_UV * np.einsum("ij,ejt->eit", mixing, sources[..., :n_times])

    alpha_freq = rng.normal(*_ALPHA_FREQUENCY_HZ, size=(n_epochs, 1))
    alpha_shape = np.exp(-((freqs - alpha_freq) ** 2) / (2 * _ALPHA_BANDWIDTH_HZ**2))
    alpha_scale = _ALPHA_RMS_UV * np.exp(
        rng.normal(-(_ALPHA_AMPLITUDE_SD**2) / 2, _ALPHA_AMPLITUDE_SD, size=(n_epochs, 1))
    )
    alpha = alpha_scale * _random_spectrum(rng, alpha_shape, n)[:, :n_times]
    topography = _topography(positions, _OZ, _ALPHA_SPREAD)
    return background + topography[None, :, None] * alpha[:, None, :]


def _evoked(
    rng: np.random.Generator,
    waves: Sequence[_Wave],
    scale: np.ndarray,
    positions: np.ndarray,
    times: np.ndarray,
) -> np.ndarray:
    """Jittered response of every epoch times ``scale`` (n_epochs,): (n_epochs, n_ch, n_times).

    Every epoch draws its latency shift and amplitude factor (shared by the waves), so the
    draws do not depend on ``scale``.
    """
    n_epochs = len(scale)
    shift = rng.normal(0.0, _LATENCY_JITTER_S, size=(n_epochs, 1))
    factor = np.exp(rng.normal(-(_AMPLITUDE_JITTER**2) / 2, _AMPLITUDE_JITTER, size=n_epochs))
    response = np.zeros((n_epochs, len(positions), len(times)))
    for wave in waves:
        course = np.exp(-((times - wave.latency - shift) ** 2) / (2 * wave.width**2))
        topography = _topography(positions, wave.centre, _TOPOGRAPHY_SPREAD)
        response += wave.amplitude * topography[None, :, None] * course[:, None, :]
    return (scale * factor)[:, None, None] * response


def _theta_burst(
    rng: np.random.Generator, is_error: np.ndarray, positions: np.ndarray, times: np.ndarray
) -> np.ndarray:
    """Random-phase frontal theta after errors, shape (n_epochs, n_channels, n_times)."""
    n_epochs = len(is_error)
    phase = rng.uniform(0.0, 2 * np.pi, size=(n_epochs, 1))
    # Rayleigh amplitudes with mean _THETA_AMPLITUDE_UV.
    amplitude = rng.rayleigh(_THETA_AMPLITUDE_UV / math.sqrt(math.pi / 2), size=(n_epochs, 1))
    envelope = np.exp(-((times - _THETA_LATENCY_S) ** 2) / (2 * _THETA_WIDTH_S**2))
    burst = amplitude * envelope * np.cos(2 * np.pi * _THETA_FREQUENCY_HZ * times + phase)
    topography = _topography(positions, _FCZ, _TOPOGRAPHY_SPREAD)
    return (is_error[:, None] * burst)[:, None, :] * topography[None, :, None]
