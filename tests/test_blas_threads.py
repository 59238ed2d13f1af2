"""``cfbci --blas-threads N``: the BLAS threads of a command and of its children."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from threadpoolctl import threadpool_info

from cfbci.blas import single_threaded_blas
from cfbci.cli import main


def _blas_threads() -> set[int]:
    return {pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"}


@pytest.fixture
def restores_one_thread():
    yield
    single_threaded_blas()  # the process's (and the other tests') setting
    assert _blas_threads() == {1} and os.environ["OPENBLAS_NUM_THREADS"] == "1"


def test_the_option_sets_the_threads_of_the_process_and_its_children(
    tmp_path: Path, restores_one_thread
) -> None:
    rng = np.random.default_rng(0)
    labels = np.arange(120) % 2
    dataset = tmp_path / "data.npz"
    np.savez(dataset, features=rng.normal(size=(120, 4)) + labels[:, None], labels=labels)
    args = ["simulate", "--dataset", str(dataset), "--seeds", "1", "--steps", "15"]
    assert main(["--blas-threads", "2", *args]) == 0
    assert _blas_threads() == {2}
    assert os.environ["OPENBLAS_NUM_THREADS"] == "2"  # what child processes start with
    assert main(args) == 0  # the default is one
    assert _blas_threads() == {1}


def test_zero_threads_is_refused(capsys, restores_one_thread) -> None:
    assert main(["--blas-threads", "0", "world", "check", "--world", "line"]) == 2
    assert "--blas-threads must be >= 1; got 0" in capsys.readouterr().err
