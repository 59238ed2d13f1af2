"""``cfbci datasets speech``: write the synthesised speech dataset (:mod:`acquisition.speech`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from rich.console import Console

from acquisition.loaders import save_features_npz
from acquisition.speech import (
    DISTRACTOR_WORDS,
    GUIDANCE_WORDS,
    VARIANTS,
    VOICES,
    SpeechParameters,
    speech_dataset,
)


def add_datasets_command(commands: argparse._SubParsersAction) -> None:
    """Register ``cfbci datasets speech``."""
    p = commands.add_parser("datasets", help="make the datasets the project synthesises")
    which = p.add_subparsers(dest="dataset", required=True)
    speech = which.add_parser(
        "speech",
        help="spoken words (espeak-ng) as 20 DTW distances of MFCC frames, in a features .npz",
    )
    speech.add_argument("--utterances-per-word", type=int, default=100)
    speech.add_argument(
        "--words", default=",".join(GUIDANCE_WORDS),
        help="comma-separated meaning words, class 0 first (default: pick-and-place guidance "
        "right,left,grasp,release; feedback: yes,no = correct,error)",
    )
    speech.add_argument(
        "--distractors", default=",".join(DISTRACTOR_WORDS),
        help="comma-separated extra words scored beside the meanings, not written ('' for none)",
    )
    speech.add_argument("--seed", type=int, default=0)
    speech.add_argument(
        "--snr-db", default=None, metavar="LO,HI",
        help="range of the added white noise's signal-to-noise ratio, dB (default -3,12: "
        "decoded at 0.88-0.94, not trivially; the thesis's recorded words were decoded at "
        "close to 100 %%)",
    )
    speech.add_argument(
        "--speaker", default=None, metavar="VOICE+VARIANT",
        help="one espeak-ng speaker for every utterance (e.g. en-gb+m3), like the thesis's "
        "single teacher (default: a voice and variant drawn per utterance)",
    )
    speech.add_argument("--out", type=Path, required=True, help="features .npz to write")
    speech.set_defaults(run=_run_speech)


def _words(text: str) -> list[str]:
    return [w.strip() for w in text.split(",") if w.strip()]


def _snr_range(text: str) -> tuple[float, float]:
    """``--snr-db LO,HI`` as (LO, HI) dB."""
    try:
        low, high = (float(x) for x in text.split(","))
    except ValueError:
        raise ValueError(f"--snr-db must be two numbers LO,HI (dB); got {text!r}") from None
    if not low <= high:
        raise ValueError(f"--snr-db needs LO <= HI; got {text!r}")
    return low, high


def _parameters(args: argparse.Namespace) -> SpeechParameters:
    """The speech parameters ``--snr-db`` and ``--speaker`` change from the defaults."""
    changes: dict[str, object] = {}
    if args.snr_db:
        changes["snr_db"] = _snr_range(args.snr_db)
    if args.speaker:
        voice, plus, variant = args.speaker.partition("+")
        if not plus or voice not in VOICES or variant not in VARIANTS:
            raise ValueError(
                f"--speaker must be VOICE+VARIANT, a voice of {', '.join(VOICES)} and a "
                f"variant of {', '.join(VARIANTS)}; got {args.speaker!r}"
            )
        changes.update(voices=(voice,), variants=(variant,))
    return SpeechParameters(**changes)  # type: ignore[arg-type]


def _run_speech(args: argparse.Namespace, console: Console) -> int:
    words = _words(args.words)
    if len(words) < 2:
        raise ValueError(f"--words needs at least two words; got {args.words!r}")
    if args.utterances_per_word < 10:
        raise ValueError(
            "--utterances-per-word must be >= 10 (10-fold cross-validation needs them); "
            f"got {args.utterances_per_word}"
        )
    parameters = _parameters(args)
    with console.status(f"synthesising {len(words)} words x {args.utterances_per_word}"):
        data, accuracy = speech_dataset(
            words, args.utterances_per_word, args.seed, _words(args.distractors), parameters
        )
    save_features_npz(args.out, data.features, data.labels)
    console.print(
        f"{args.out}: {data.features.shape[0]} utterances x {data.features.shape[1]} features; "
        + ", ".join(f"{k} = {w}" for k, w in enumerate(data.words))
    )
    console.print(f"10-fold balanced LDA accuracy: {accuracy.meanings:.3f}")
    if accuracy.with_distractors is not None:
        console.print(
            f"  with {accuracy.n_distractors} distractor words as extra classes: "
            f"{accuracy.with_distractors:.3f}"
        )
    return 0
