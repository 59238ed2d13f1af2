"""Programs from Debian's packages some tests drive (Chromium and its driver, espeak-ng,
openssl, node and npm): a test that needs one skips, naming the package to install, when
it is absent, unless ``CFBCI_REQUIRE_SYSTEM_DEPS=1`` (set by ``.ci/run`` after installing
them), where its absence fails the test, so that CI runs every test."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

#: The environment variable that turns a missing program into a failure.
REQUIRE = "CFBCI_REQUIRE_SYSTEM_DEPS"


def require(program: str, package: str, debian_path: str | None = None) -> str:
    """The path of ``program``; skip (or fail, under `REQUIRE`) when it is absent,
    naming ``package``, the Debian package that installs it."""
    found = shutil.which(program) or (
        debian_path if debian_path is not None and Path(debian_path).exists() else None
    )
    if found is not None:
        return found
    message = f"needs {program}: apt-get install {package}"
    if os.environ.get(REQUIRE) == "1":
        pytest.fail(f"{message} ({REQUIRE}=1: every test must run)")
    pytest.skip(message)
