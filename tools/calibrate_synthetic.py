"""Measure the difficulty curve of the synthetic ErrP generator and print its table.

For each gain of a grid, `acquisition.synthetic.generate_errp_epochs_at_gain` draws
``--n-correct`` correct and ``--n-error`` error epochs for each of ``--seeds`` seeds; the
score is the balanced accuracy of a shrinkage LDA (``solver="lsqr", shrinkage=0.5``, equal
priors) on `decoding.features.ErrPFeatures` features, 10-fold stratified
cross-validation, averaged over the seeds. The printed constants are the calibration table
of `acquisition.synthetic`; the extra columns (power ratio error / correct of the
feature vectors, standard error of the mean accuracy) are for information.

``--verify`` instead generates epochs with `acquisition.synthetic.generate_errp_epochs`
at a few nominal accuracies (on seeds other than the calibration ones) and prints the
achieved accuracy.

Usage::

    .venv/bin/python tools/calibrate_synthetic.py [--seeds 40] [--verify]
"""

from __future__ import annotations

import argparse

import numpy as np
from sklearn.discriminant_analysis import LinearDiscriminantAnalysis
from sklearn.model_selection import StratifiedKFold, cross_val_score

from acquisition.labelled import LabelledEpochs
from acquisition.synthetic import generate_errp_epochs, generate_errp_epochs_at_gain
from decoding.features import ErrPFeatures

GAINS = np.round(np.arange(0.0, 4.01, 0.2), 2)
NOMINAL = (0.55, 0.6, 0.65, 0.7, 0.78, 0.85, 0.9, 0.95, 0.97)
# Verification seeds start here, away from the calibration seeds 0..n_seeds-1.
VERIFY_SEED_OFFSET = 10_000


def score(data: LabelledEpochs) -> tuple[float, float]:
    """Balanced 10-fold accuracy of the shrinkage LDA, and the error / correct power ratio."""
    features = ErrPFeatures(data.sfreq, data.tmin, data.ch_names).fit_transform(data.epochs)
    lda = LinearDiscriminantAnalysis(solver="lsqr", shrinkage=0.5, priors=[0.5, 0.5])
    accuracy = cross_val_score(
        lda, features, data.labels, cv=StratifiedKFold(10), scoring="balanced_accuracy"
    ).mean()
    power = np.sum(features**2, axis=1)
    ratio = power[data.labels == 1].mean() / power[data.labels == 0].mean()
    return float(accuracy), float(ratio)


def calibrate(n_seeds: int, n_correct: int, n_error: int) -> None:
    """Print the accuracy at each gain of ``GAINS`` and the table constants."""
    accuracies = []
    print(f"{'gain':>6} {'accuracy':>9} {'sem':>7} {'power ratio':>12}")
    for gain in GAINS:
        scores = np.array(
            [
                score(generate_errp_epochs_at_gain(n_correct, n_error, gain=gain, seed=seed))
                for seed in range(n_seeds)
            ]
        )
        mean = scores.mean(axis=0)
        sem = scores[:, 0].std(ddof=1) / np.sqrt(n_seeds)
        accuracies.append(mean[0])
        print(f"{gain:6.2f} {mean[0]:9.4f} {sem:7.4f} {mean[1]:12.3f}", flush=True)
    if np.any(np.diff(accuracies) <= 0):
        print("WARNING: the accuracy is not strictly increasing with the gain")
    print()
    print(python_tuple("_CALIBRATION_GAIN", [f"{g:.1f}" for g in GAINS]))
    print(python_tuple("_CALIBRATION_ACCURACY", [f"{a:.4f}" for a in accuracies]))


def python_tuple(name: str, values: list[str]) -> str:
    """Python source of the constant ``name = (values...)``, 11 values a line."""
    lines = [", ".join(values[i : i + 11]) + "," for i in range(0, len(values), 11)]
    return f"{name} = (\n" + "".join(f"    {line}\n" for line in lines) + ")  # fmt: skip"


def verify(n_seeds: int, n_correct: int, n_error: int) -> None:
    """Print the achieved accuracy of `generate_errp_epochs` at nominal accuracies."""
    print(f"{'nominal':>8} {'achieved':>9} {'sem':>7} {'power ratio':>12}")
    seeds = range(VERIFY_SEED_OFFSET, VERIFY_SEED_OFFSET + n_seeds)
    for nominal in NOMINAL:
        scores = np.array(
            [
                score(generate_errp_epochs(n_correct, n_error, accuracy=nominal, seed=seed))
                for seed in seeds
            ]
        )
        mean = scores.mean(axis=0)
        sem = scores[:, 0].std(ddof=1) / np.sqrt(n_seeds)
        print(f"{nominal:8.2f} {mean[0]:9.4f} {sem:7.4f} {mean[1]:12.3f}", flush=True)


def main() -> None:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=40, help="seeds per gain (default 40)")
    parser.add_argument("--n-correct", type=int, default=800)
    parser.add_argument("--n-error", type=int, default=200)
    parser.add_argument(
        "--verify", action="store_true", help="check generate_errp_epochs against nominal"
    )
    args = parser.parse_args()
    run = verify if args.verify else calibrate
    run(args.seeds, args.n_correct, args.n_error)


if __name__ == "__main__":
    main()
