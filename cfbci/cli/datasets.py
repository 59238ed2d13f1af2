"""``cfbci datasets``: ``fetch`` and ``path`` of the public real data sets
(`acquisition.fetch`), ``speech`` writes the synthesised speech dataset
(`acquisition.speech`)."""

from __future__ import annotations

import argparse
import textwrap
from pathlib import Path

from rich.console import Console
from rich.markup import escape

from acquisition.fetch import (
    DATASETS,
    DEFAULT_URL,
    FOLDER_VARIABLE,
    URL_VARIABLE,
    FetchError,
    data_folder,
    fetch,
    fetched_path,
)
from acquisition.speech import (
    DISTRACTOR_WORDS,
    GUIDANCE_WORDS,
    VARIANTS,
    VOICES,
    SpeechParameters,
    speech_dataset,
)

_LICENCE_NOTE = (
    "Both files are J. Grizou's public research data, under the GNU GPL v2 (GPL-2.0): each "
    "user downloads them from their public source; cfbci does not redistribute them."
)


def add_datasets_command(commands: argparse._SubParsersAction) -> None:
    """Register ``cfbci datasets fetch``, ``cfbci datasets path`` and ``cfbci datasets speech``."""
    p = commands.add_parser(
        "datasets", help="fetch the public real datasets, or make the ones the project synthesises"
    )
    which = p.add_subparsers(dest="dataset", required=True)
    _add_fetch(which)
    _add_path(which)
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


def _fetch_description() -> str:
    """``cfbci datasets fetch``'s help: what it does, the pinned files, licence, folders."""
    files = "\n".join(
        f"  {d.name}: {d.title}\n    {d.path} of github.com/{d.repository}, licence "
        f"{d.licence}\n    commit {d.commit}\n    sha256 {d.sha256}"
        for d in DATASETS.values()
    )
    paragraphs = (
        "Download the public real datasets the documentation uses, each pinned to a commit "
        "and checked by its sha256 (a mismatch is refused and nothing is kept); a file "
        "already fetched intact is not downloaded again.",
        files,
        _LICENCE_NOTE,
        f"Files are kept in ${FOLDER_VARIABLE} if set, else the user's cache folder (here "
        f"{data_folder()}). ${URL_VARIABLE} replaces the source's base address "
        f"{DEFAULT_URL} with a mirror's: each file is fetched from "
        "BASE/OWNER/REPOSITORY/COMMIT/PATH.",
    )
    return "\n\n".join(
        text if text is files else textwrap.fill(text, 79) for text in paragraphs
    )


def _add_fetch(which: argparse._SubParsersAction) -> None:
    fetch_parser = which.add_parser(
        "fetch",
        help="download the public real datasets (GPL-2.0, from their source) into the cache",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=_fetch_description(),
    )
    fetch_parser.add_argument(
        "name", choices=[*DATASETS, "all"], help="the dataset to download, or all of them"
    )
    fetch_parser.set_defaults(run=_run_fetch)


def _add_path(which: argparse._SubParsersAction) -> None:
    path_parser = which.add_parser(
        "path",
        help="print where a fetched dataset lies, e.g. cfbci simulate --dataset "
        '"$(cfbci datasets path s4)"',
        description="Print the path of a dataset `cfbci datasets fetch` downloaded (its "
        "sha256 checked); exit status 1 if it is not fetched yet.",
    )
    path_parser.add_argument("name", choices=list(DATASETS), help="the dataset")
    path_parser.set_defaults(run=_run_path)


def _error(error: FetchError) -> int:
    """Print a fetch error on stderr; exit status 1."""
    Console(stderr=True).print(
        f"[bold red]error:[/] {escape(str(error))}", soft_wrap=True, highlight=False
    )
    return 1


def _run_fetch(args: argparse.Namespace, console: Console) -> int:
    status = 0
    for name in list(DATASETS) if args.name == "all" else [args.name]:
        try:
            path = fetch(name)
        except FetchError as error:  # report it, and still fetch the others
            status = _error(error)
            continue
        console.print(
            f"{name}: {path} ({DATASETS[name].licence})", soft_wrap=True, markup=False,
            highlight=False,
        )
    return status


def _run_path(args: argparse.Namespace, console: Console) -> int:
    try:
        path = fetched_path(args.name)
    except FetchError as error:
        return _error(error)
    print(path)  # plain: the whole line is the path, for "$(cfbci datasets path NAME)"
    return 0


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
    from acquisition.loaders import save_features_npz  # scipy: only this command's

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
