"""How a dataset's decoders fare at each shrinkage: the table behind ``shrinkage="cv"``.

For ``--draws`` random subsets of ``--signals`` labelled signals (seeded), at every
shrinkage of the grid: the balanced accuracy on the remaining signals of the project's
shrinkage LDA (`decoding.lda.ShrinkageLDA`, equal priors) fitted on the subset, and
the discriminability of the learner's cross-validated matching evidence on the subset
(`calibration_free.shrinkage_choice.evidence_discriminability`, eps 0.1, 10 folds);
then the shrinkage the learner would choose (`
choose_shrinkage`), as counts over the draws. Feedback (two-class) data only.

Usage::

    .venv/bin/python tools/shrinkage_curves.py synthetic [--accuracy 0.78]
    .venv/bin/python tools/shrinkage_curves.py mixed [--dims 34 --decay 2 --accuracy 0.9]
    .venv/bin/python tools/shrinkage_curves.py ../shared/datasets/errp-features-s4/s4.mat
"""

from __future__ import annotations

import argparse
from collections import Counter

import numpy as np

from acquisition.gaussian import generate_gaussian_features
from acquisition.labelled import LabelledFeatures
from acquisition.loaders import load_labelled
from acquisition.sources import SYNTHETIC_EPOCHS_PER_CLASS, synthetic_features
from calibration_free.shrinkage_choice import (
    choose_shrinkage,
    evidence_discriminability,
    labelled_history,
)
from decoding.lda import ShrinkageLDA

GRID = (0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 0.9)


def load(args: argparse.Namespace) -> LabelledFeatures:
    """The dataset named on the command line."""
    rng = np.random.default_rng(0)
    if args.data == "synthetic":
        return synthetic_features(args.accuracy, rng)
    if args.data == "mixed":
        return generate_gaussian_features(
            SYNTHETIC_EPOCHS_PER_CLASS, 2, args.dims, args.accuracy, rng, args.decay
        )
    return load_labelled(args.data)


def balanced_accuracy(labels: np.ndarray, predicted: np.ndarray) -> float:
    """Mean recall of the two classes."""
    return float(np.mean([np.mean(predicted[labels == k] == k) for k in (0, 1)]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("data", help="'synthetic', 'mixed', or a feedback dataset file")
    parser.add_argument("--accuracy", type=float, default=0.78)
    parser.add_argument("--dims", type=int, default=34)
    parser.add_argument("--decay", type=float, default=2.0)
    parser.add_argument("--signals", type=int, default=300)
    parser.add_argument("--draws", type=int, default=10)
    args = parser.parse_args()
    data = load(args)
    features, labels = data.features.astype(float), data.labels
    rng = np.random.default_rng(1)
    accuracy, discriminability, chosen = [], [], Counter()
    for _ in range(args.draws):
        subset = rng.choice(len(labels), args.signals, replace=False)
        rest = np.setdiff1d(np.arange(len(labels)), subset)
        X = features[subset]
        history = labelled_history(X, np.eye(2)[labels[subset]])
        accuracy.append([
            balanced_accuracy(
                labels[rest], ShrinkageLDA(s).fit(X, labels[subset]).predict(features[rest])
            )
            for s in GRID
        ])
        discriminability.append(
            evidence_discriminability(history, 0, GRID, eps=0.1, smoothing=1.0)
        )
        chosen[choose_shrinkage(history, 0, eps=0.1, smoothing=1.0)] += 1
    print(f"{data.source}: {args.draws} draws of {args.signals} signals")
    print("shrinkage        " + " ".join(f"{s:>6}" for s in GRID))
    print("accuracy         " + " ".join(f"{v:6.3f}" for v in np.mean(accuracy, axis=0)))
    print("discriminability " + " ".join(f"{v:6.3f}" for v in np.mean(discriminability, axis=0)))
    print("chosen (cv)      " + ", ".join(f"{s}: {n}" for s, n in sorted(chosen.items())))


if __name__ == "__main__":
    main()
