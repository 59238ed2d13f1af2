"""ErrP feature vectors from raw EEG epochs (method.md section 8).

The published pipeline: band-pass 1-10 Hz, channels Fz, FCz, Cz, the window 200-800 ms after
the action onset, decimated to 32 Hz; the feature vector is the concatenated samples in
microvolts. At 256 Hz with the three channels that is 3 x 19 = 57 features.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.signal import butter, sosfiltfilt
from sklearn.base import BaseEstimator, TransformerMixin
from sklearn.utils.validation import check_is_fitted

from decoding.validation import check_array, check_range

#: Order of the Butterworth band-pass (``scipy.signal.butter(N=4, btype="bandpass")``).
FILTER_ORDER = 4
# Tolerance on times expressed in samples, so that e.g. 0.2 s * 256 Hz counts as a whole
# number of samples despite floating-point rounding.
_SAMPLE_TOLERANCE = 1e-6


class ErrPFeatures(TransformerMixin, BaseEstimator):
    """Band-passed, decimated fronto-central samples after the action onset.

    Each epoch is filtered on its own (zero-phase Butterworth band-pass over the whole
    epoch, along time), then the samples of the selected channels inside ``window`` are
    kept at ``decimate_to`` Hz and concatenated channel by channel. The result of an epoch
    does not depend on the other epochs of the batch.

    Filter edges: `scipy.signal.sosfiltfilt` pads each end of the epoch with its edge
    value over the whole epoch length (``padtype="constant", padlen=n_times - 1``) instead
    of its default odd extension of 27 samples. With a 1 Hz high-pass on a 1.2 s epoch the
    edge transients reach into the window; on synthetic 1/f EEG the window samples differ
    from those of the filtered continuous recording by about 12 % (RMS) with this padding
    and 25 % with the default.

    Window sampling: the window holds ``n = floor((window[1] - window[0]) * decimate_to)``
    decimated samples, the number of whole decimation periods that fit in it. The first
    one is the first raw sample at or after ``window[0]``; the others follow every
    ``sfreq / decimate_to`` raw samples. Each decimated sample therefore starts a full
    ``1 / decimate_to`` s bin lying inside the window. For the default window [0.2, 0.8] s
    at 32 Hz, n = floor(19.2) = 19 samples; at 256 Hz with the onset on a sample they lie
    at 52 / 256 = 0.203 s, then every 8 samples up to 0.766 s.

    Parameters
    ----------
    sfreq : float
        Sampling frequency of the epochs, in Hz. Must be an integer multiple of
        ``decimate_to``.
    tmin : float
        Time of the first sample of each epoch relative to the action onset, in s
        (e.g. -0.2).
    ch_names : sequence of str, length n_channels
        Names of the channels of the epochs, in the order of their channel axis.
    channels : sequence of str, default ("Fz", "FCz", "Cz")
        Wanted channels. Those present in ``ch_names`` are used, in this order; at least
        one must be present.
    l_freq, h_freq : float, default 1.0 and 10.0
        Pass band of the filter, in Hz; ``0 < l_freq < h_freq < sfreq / 2``.
    window : (float, float), default (0.2, 0.8)
        Start and end of the feature window, in s after the action onset.
    decimate_to : float, default 32.0
        Sampling frequency of the features, in Hz.

    Attributes
    ----------
    picks_ : ndarray, shape (n_selected_channels,), int
        Indices of the selected channels in ``ch_names``.
    selected_channels_ : tuple of str, length n_selected_channels
        Names of the selected channels, in feature order.
    sos_ : ndarray, shape (n_sections, 6)
        Second-order sections of the band-pass filter.
    sample_indices_ : ndarray, shape (n_window_samples,), int
        Indices on the time axis of the epochs of the kept samples.
    times_ : ndarray, shape (n_window_samples,), float
        Times of the kept samples relative to the action onset, in s.
    n_features_out_ : int
        Length of a feature vector, ``n_selected_channels * n_window_samples``.

    Examples
    --------
    >>> import numpy as np
    >>> epochs = np.zeros((5, 4, 308))  # 5 epochs, 4 channels, -0.2 s to 1.0 s at 256 Hz
    >>> features = ErrPFeatures(256.0, -0.2, ["Fz", "FCz", "Cz", "Pz"])
    >>> features.fit_transform(epochs).shape
    (5, 57)
    """

    def __init__(
        self,
        sfreq: float,
        tmin: float,
        ch_names: Sequence[str],
        channels: Sequence[str] = ("Fz", "FCz", "Cz"),
        l_freq: float = 1.0,
        h_freq: float = 10.0,
        window: tuple[float, float] = (0.2, 0.8),
        decimate_to: float = 32.0,
    ) -> None:
        self.sfreq = sfreq
        self.tmin = tmin
        self.ch_names = ch_names
        self.channels = channels
        self.l_freq = l_freq
        self.h_freq = h_freq
        self.window = window
        self.decimate_to = decimate_to

    def fit(self, X: Any, y: Any = None) -> ErrPFeatures:
        """Check the parameters and the epochs, and design the filter and sample grid.

        Parameters
        ----------
        X : array-like, shape (n_epochs, n_channels, n_times)
            EEG epochs in microvolts (only their shape is used).
        y : None
            Ignored; present for the scikit-learn API.

        Returns
        -------
        self : ErrPFeatures
            The fitted transformer.
        """
        sfreq = check_range("sfreq", float(self.sfreq), 0.0, math.inf, inclusive=False)
        decimate_to = check_range(
            "decimate_to", float(self.decimate_to), 0.0, math.inf, inclusive=False
        )
        factor = sfreq / decimate_to
        if round(factor) < 1 or abs(factor - round(factor)) > _SAMPLE_TOLERANCE * factor:
            raise ValueError(
                f"sfreq ({sfreq} Hz) must be an integer multiple of decimate_to "
                f"({decimate_to} Hz); their ratio is {factor:.6g}"
            )
        decimation = round(factor)

        check_range("l_freq", float(self.l_freq), 0.0, sfreq / 2, inclusive=False)
        check_range("h_freq", float(self.h_freq), float(self.l_freq), sfreq / 2, inclusive=False)

        ch_names = tuple(self.ch_names)
        if len(set(ch_names)) != len(ch_names):
            raise ValueError(f"ch_names holds duplicate names: {ch_names}")
        wanted = tuple(self.channels)
        selected = tuple(ch for ch in wanted if ch in ch_names)
        if not selected:
            raise ValueError(
                f"none of the wanted channels {wanted} is in ch_names; available: {ch_names}"
            )

        start, stop = (float(t) for t in self.window)
        n_window = math.floor((stop - start) * decimate_to + _SAMPLE_TOLERANCE)
        if n_window < 1:
            raise ValueError(
                f"window {self.window} s is shorter than one sample at decimate_to = "
                f"{decimate_to} Hz"
            )
        first = math.ceil((start - float(self.tmin)) * sfreq - _SAMPLE_TOLERANCE)
        if first < 0:
            raise ValueError(
                f"window starts at {start} s, before the first sample of the epochs "
                f"(tmin = {self.tmin} s)"
            )
        sample_indices = first + decimation * np.arange(n_window)
        self._check_epochs(X, sample_indices)

        self.picks_ = np.array([ch_names.index(ch) for ch in selected])
        self.selected_channels_ = selected
        self.sos_ = butter(
            FILTER_ORDER, [self.l_freq, self.h_freq], btype="bandpass", fs=sfreq, output="sos"
        )
        self.sample_indices_ = sample_indices
        self.times_ = float(self.tmin) + sample_indices / sfreq
        self.n_features_out_ = len(selected) * n_window
        return self

    def transform(self, X: Any) -> np.ndarray:
        """Compute the feature vectors of epochs.

        Parameters
        ----------
        X : array-like, shape (n_epochs, n_channels, n_times)
            EEG epochs in microvolts, any float dtype; computations are in float64.
            ``n_times`` may differ from the fitted epochs but must cover the window.

        Returns
        -------
        features : ndarray, shape (n_epochs, n_selected_channels * n_window_samples), float64
            Microvolts; all samples of the first selected channel, then of the second, ...
        """
        check_is_fitted(self, "sos_")
        epochs = self._check_epochs(X, self.sample_indices_)[:, self.picks_, :]
        filtered = sosfiltfilt(
            self.sos_, epochs, axis=-1, padtype="constant", padlen=epochs.shape[-1] - 1
        )
        return filtered[:, :, self.sample_indices_].reshape(len(epochs), -1)

    def get_feature_names_out(self, input_features: Any = None) -> np.ndarray:
        """Names of the features, ``"<channel>_<time in ms>ms"`` in feature order.

        Parameters
        ----------
        input_features : None
            Ignored: the input is epochs, not named features. Present for the
            scikit-learn API (e.g. `sklearn.pipeline.Pipeline.get_feature_names_out`).

        Returns
        -------
        names : ndarray, shape (n_features_out_,), object
        """
        check_is_fitted(self, "sos_")
        return np.array(
            [f"{ch}_{1000 * t:.1f}ms" for ch in self.selected_channels_ for t in self.times_],
            dtype=object,
        )

    def _check_epochs(self, X: Any, sample_indices: np.ndarray) -> np.ndarray:
        """``X`` as float64 epochs; checks rank, channels, finiteness, ``sample_indices``."""
        n_channels = len(self.ch_names)
        epochs = check_array("X", X, shape=(None, n_channels, None))
        n_needed = int(sample_indices[-1]) + 1
        if epochs.shape[-1] < n_needed:
            raise ValueError(
                f"X epochs have {epochs.shape[-1]} samples, too short: the window "
                f"{self.window} s with tmin = {self.tmin} s at {self.sfreq} Hz needs at "
                f"least {n_needed}"
            )
        return epochs
