"""Synthesised speech features: spoken words as 20-D vectors of DTW distances (thesis ch. 4).

The thesis's speech recordings are not public, so this module makes a stand-in with a
real speech path. Each utterance of a word is synthesised by espeak-ng (Debian package
``espeak-ng``) with a voice, speed and pitch drawn from a seeded generator, mixed with
white noise at a drawn signal-to-noise ratio, and turned into a sequence of 12-D MFCC frames
(librosa). Its feature vector is its 20 dynamic-time-warping distances to 20 fixed
reference words that the teacher never says (the thesis's list), each reference spoken
once by the default voice. Everything after the synthesiser is deterministic, and the
synthesiser is deterministic for fixed parameters, so a seed gives the same features.

Parameters (fixed, documented; `SpeechParameters` holds them):

* voices: espeak-ng's English voices in `VOICES` (British, American, Scottish,
  Caribbean, Received Pronunciation, West Midlands, Lancaster, New York City), each with a
  random variant (male ``m1``..``m7`` or female ``f1``..``f5``),
* speed: uniform 120..200 words per minute; pitch: uniform 20..80 (espeak-ng's 0..99 scale),
* noise: white Gaussian noise at a signal-to-noise ratio uniform in -3..12 dB (power of the
  utterance's samples over the noise's),
* MFCC: 22,050 Hz (espeak-ng's rate), 25 ms windows (n_fft 551), 10 ms hop, 40 mel bands,
  coefficients 1..12 (the 0th, the log energy, is dropped, so loudness does not count),
* DTW: Euclidean frame distance, the accumulated cost of the optimal path divided by the
  sum of the two sequences' lengths (so that long words are not far from everything).

*Distractors* are extra words (`DISTRACTOR_WORDS`) spoken by the same random voices;
they are not written to the dataset (a dataset holds one class per meaning) but are scored
beside it: `accuracy_report` gives the 10-fold balanced LDA accuracy of the meaning
words alone (what a learner decodes) and with the distractors as extra classes (how well the
features set the meaning words apart from other speech).
"""

from __future__ import annotations

import io
import shutil
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: The thesis's 20 reference words (ch. 4), which the teacher never says.
REFERENCE_WORDS: tuple[str, ...] = (
    "error", "acquisition", "difficulties", "semantic", "track", "computer", "explored",
    "distribution", "century", "reinforcement", "almost", "language", "alone", "kinds",
    "humans", "axons", "primitives", "vision", "nature", "building",
)
#: Default meaning words: pick-and-place guidance, classes 0..3 = right, left, grasp, release.
GUIDANCE_WORDS: tuple[str, ...] = ("right", "left", "grasp", "release")
#: Meaning words of the feedback frame, 0 = correct ("yes"), 1 = error ("no").
FEEDBACK_WORDS: tuple[str, ...] = ("yes", "no")
#: Extra words scored beside the meaning words, never written to the dataset.
DISTRACTOR_WORDS: tuple[str, ...] = ("stop", "again", "light")
#: espeak-ng's English voices the speakers are drawn from.
VOICES: tuple[str, ...] = (
    "en-gb", "en-us", "en-gb-scotland", "en-029", "en-gb-x-rp", "en-gb-x-gbcwmd",
    "en-gb-x-gbclan", "en-us-nyc",
)
#: espeak-ng's voice variants (male m1..m7, female f1..f5).
VARIANTS = tuple(f"m{i}" for i in range(1, 8)) + tuple(f"f{i}" for i in range(1, 6))
_REFERENCE_VOICE = "en-gb"
SAMPLE_RATE = 22050  # Hz, espeak-ng's output rate


@dataclass(frozen=True)
class SpeechParameters:
    """The draws of the synthetic speakers and the feature settings (see the module docstring).

    Attributes
    ----------
    speed_wpm : tuple of float
        Range of espeak-ng's speed, words per minute.
    pitch : tuple of float
        Range of espeak-ng's pitch (0..99).
    snr_db : tuple of float
        Range of the signal-to-noise ratio of the added white noise, dB.
    n_mfcc : int
        MFCC coefficients kept per frame (coefficients 1..n_mfcc).
    window_s, hop_s : float
        MFCC window and hop, seconds.
    n_mels : int
        Mel bands.
    voices, variants : tuple of str
        espeak-ng voices and variants the speakers are drawn from (one of each: a single
        speaker, like the thesis's one teacher).
    """

    speed_wpm: tuple[float, float] = (120.0, 200.0)
    pitch: tuple[float, float] = (20.0, 80.0)
    snr_db: tuple[float, float] = (-3.0, 12.0)
    n_mfcc: int = 12
    window_s: float = 0.025
    hop_s: float = 0.010
    n_mels: int = 40
    voices: tuple[str, ...] = VOICES
    variants: tuple[str, ...] = VARIANTS


@dataclass(frozen=True)
class SpeechDataset:
    """Feature vectors of spoken words.

    Attributes
    ----------
    features : ndarray, shape (n_utterances, n_references)
        DTW distances of each utterance to each reference word (MFCC units per frame).
    labels : ndarray of int, shape (n_utterances,)
        Index of the utterance's word in ``words``.
    words : tuple of str
        The words, in class order.
    """

    features: np.ndarray
    labels: np.ndarray
    words: tuple[str, ...]


def espeak_executable() -> str:
    """The espeak-ng executable.

    Raises
    ------
    FileNotFoundError
        If espeak-ng is not installed, with the command that installs it.
    """
    path = shutil.which("espeak-ng")
    if path is None:
        raise FileNotFoundError(
            "espeak-ng is not installed: the speech dataset is synthesised with it "
            "(Debian: apt-get install espeak-ng)"
        )
    return path


def synthesise(word: str, voice: str, speed_wpm: float, pitch: float) -> np.ndarray:
    """One utterance of ``word`` by espeak-ng.

    Returns
    -------
    ndarray of float64, shape (n_samples,)
        The waveform at `SAMPLE_RATE` Hz, in [-1, 1].
    """
    import soundfile

    command = [
        espeak_executable(), "-v", voice, "-s", str(round(speed_wpm)), "-p", str(round(pitch)),
        "--stdout", word,
    ]
    wav = subprocess.run(command, capture_output=True, check=True).stdout
    samples, rate = soundfile.read(io.BytesIO(wav), dtype="float64")
    if rate != SAMPLE_RATE or samples.size == 0:
        raise RuntimeError(f"espeak-ng gave {samples.size} samples at {rate} Hz for {word!r}")
    return samples


def mfcc_frames(samples: np.ndarray, parameters: SpeechParameters) -> np.ndarray:
    """MFCC frames of a waveform at `SAMPLE_RATE`.

    Returns
    -------
    ndarray, shape (n_mfcc, n_frames)
        Coefficients 1..n_mfcc of each frame.
    """
    import librosa

    n_fft = round(parameters.window_s * SAMPLE_RATE)
    coefficients = librosa.feature.mfcc(
        y=samples, sr=SAMPLE_RATE, n_mfcc=parameters.n_mfcc + 1, n_fft=n_fft,
        hop_length=round(parameters.hop_s * SAMPLE_RATE), n_mels=parameters.n_mels,
    )
    return coefficients[1:]


def dtw_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Accumulated Euclidean cost of the optimal DTW path between two MFCC sequences,
    divided by the sum of their lengths (``a``, ``b``: shape (n_mfcc, n_frames))."""
    import librosa

    cost, _ = librosa.sequence.dtw(X=a, Y=b, metric="euclidean")
    return float(cost[-1, -1]) / (a.shape[1] + b.shape[1])


def _noisy(samples: np.ndarray, snr_db: float, rng: np.random.Generator) -> np.ndarray:
    noise_power = np.mean(samples**2) / 10 ** (snr_db / 10)
    return samples + rng.normal(0.0, np.sqrt(noise_power), samples.shape)


class SpeechFeatures:
    """Turns spoken words into DTW-distance vectors against the reference words.

    Parameters
    ----------
    parameters : SpeechParameters
    references : sequence of str
        The reference words, spoken once each by the default voice.
    """

    def __init__(
        self,
        parameters: SpeechParameters | None = None,
        references: Sequence[str] = REFERENCE_WORDS,
    ) -> None:
        self.parameters = parameters or SpeechParameters()
        self.references = tuple(references)
        self._reference_frames = [
            mfcc_frames(synthesise(word, _REFERENCE_VOICE, 160.0, 50.0), self.parameters)
            for word in self.references
        ]

    def utterance(self, word: str, rng: np.random.Generator) -> np.ndarray:
        """The feature vector of one utterance of ``word`` by a speaker drawn from ``rng``.

        Draws, in order: voice, variant, speed, pitch, SNR, then the noise samples.

        Returns
        -------
        ndarray, shape (n_references,)
        """
        p = self.parameters
        voice, variant = p.voices[rng.integers(len(p.voices))], p.variants[
            rng.integers(len(p.variants))]
        voice = f"{voice}+{variant}"
        speed, pitch, snr = rng.uniform(*p.speed_wpm), rng.uniform(*p.pitch), rng.uniform(*p.snr_db)
        frames = mfcc_frames(_noisy(synthesise(word, voice, speed, pitch), snr, rng), p)
        return np.array([dtw_distance(frames, ref) for ref in self._reference_frames])

    def dataset(
        self, words: Sequence[str], utterances_per_word: int, rng: np.random.Generator
    ) -> SpeechDataset:
        """``utterances_per_word`` utterances of every word, word by word.

        Returns
        -------
        SpeechDataset
            Features shape (len(words) * utterances_per_word, n_references).
        """
        if utterances_per_word < 2:
            raise ValueError(f"utterances_per_word must be >= 2; got {utterances_per_word}")
        features = np.array(
            [self.utterance(w, rng) for w in words for _ in range(utterances_per_word)]
        )
        labels = np.repeat(np.arange(len(words)), utterances_per_word)
        return SpeechDataset(features, labels, tuple(words))


def balanced_lda_accuracy(features: np.ndarray, labels: np.ndarray, seed: int = 0) -> float:
    """10-fold (stratified, shuffled with ``seed``) balanced accuracy of a shrinkage LDA
    (scikit-learn, lsqr solver, shrinkage 0.5, equal priors) on standardised features."""
    from sklearn.discriminant_analysis import LinearDiscriminantAnalysis
    from sklearn.metrics import balanced_accuracy_score
    from sklearn.model_selection import StratifiedKFold, cross_val_predict
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    n_classes = int(labels.max()) + 1
    model = make_pipeline(
        StandardScaler(),
        LinearDiscriminantAnalysis(
            solver="lsqr", shrinkage=0.5, priors=np.full(n_classes, 1 / n_classes)
        ),
    )
    folds = StratifiedKFold(10, shuffle=True, random_state=seed)
    predicted = cross_val_predict(model, features, labels, cv=folds)
    return float(balanced_accuracy_score(labels, predicted))


@dataclass(frozen=True)
class AccuracyReport:
    """Balanced 10-fold LDA accuracy of a speech dataset, alone and beside distractors."""

    meanings: float
    with_distractors: float | None
    n_classes: int
    n_distractors: int


def speech_dataset(
    words: Sequence[str],
    utterances_per_word: int,
    seed: int,
    distractors: Sequence[str] = DISTRACTOR_WORDS,
    parameters: SpeechParameters | None = None,
) -> tuple[SpeechDataset, AccuracyReport]:
    """The dataset of ``words`` and its accuracy report (distractors scored, not returned).

    The generator ``numpy.random.default_rng(seed)`` draws the meaning words' utterances
    first, then the distractors'.
    """
    rng = np.random.default_rng(seed)
    speech = SpeechFeatures(parameters)
    data = speech.dataset(words, utterances_per_word, rng)
    meanings = balanced_lda_accuracy(data.features, data.labels)
    with_distractors = None
    if distractors:
        extra = speech.dataset(distractors, utterances_per_word, rng)
        with_distractors = balanced_lda_accuracy(
            np.vstack([data.features, extra.features]),
            np.concatenate([data.labels, extra.labels + len(words)]),
        )
    return data, AccuracyReport(meanings, with_distractors, len(words), len(distractors))
