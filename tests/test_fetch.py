"""``cfbci datasets fetch`` and ``path`` (`acquisition.fetch`) against a local mirror.

The mirror is a real HTTP server on loopback serving copies of ``../shared/datasets`` laid
out as ``BASE/OWNER/REPOSITORY/COMMIT/PATH``; the cache folder is a temporary one.
``cfbci --version`` is tested here too.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import tomllib
from collections.abc import Callable, Collection, Iterator
from dataclasses import dataclass
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import numpy as np
import pooch
import pytest

from acquisition.fetch import (
    DATASETS,
    FOLDER_VARIABLE,
    URL_VARIABLE,
    base_url,
    fetch,
    fetched_path,
)
from acquisition.loaders import load_labelled
from cfbci.cli import main

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "datasets"
SHARED_FILES = {
    "s4": SHARED / "errp-features-s4" / "s4.mat",
    "finger": SHARED / "finger-moves" / "move_finger.mat",
}
needs_shared = pytest.mark.skipif(
    not all(path.is_file() for path in SHARED_FILES.values()),
    reason="real data sets absent (../shared/datasets is not in a fresh clone)",
)
#: The mirror's base address has a path, which the files' paths append to.
PREFIX = "mirror/cfbci"


@dataclass
class Mirror:
    """A local HTTP server: its base address and the paths it was asked for, in order."""

    base: str
    requests: list[str]


@pytest.fixture
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A temporary cache folder, named by ``$CFBCI_DATA_DIR`` (not created)."""
    folder = tmp_path / "cache"
    monkeypatch.setenv(FOLDER_VARIABLE, str(folder))
    return folder


@pytest.fixture
def serve(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> Iterator[Callable[..., Mirror]]:
    """Start a mirror of the shared files, ``corrupt`` ones with one byte changed, or with no
    file when ``empty``; ``$CFBCI_DATASETS_URL`` points at it."""
    running: list[tuple[ThreadingHTTPServer, threading.Thread]] = []

    def start(corrupt: Collection[str] = (), empty: bool = False) -> Mirror:
        root = tmp_path / f"served{len(running)}"
        root.mkdir()
        if not empty:
            _lay_out(root / PREFIX, corrupt)
        requests: list[str] = []

        class Handler(SimpleHTTPRequestHandler):
            def __init__(self, *args: Any, **kwargs: Any) -> None:
                super().__init__(*args, directory=str(root), **kwargs)

            def do_GET(self) -> None:
                requests.append(self.path)
                super().do_GET()

            def log_message(self, format: str, *args: Any) -> None:  # quiet test output
                pass

        server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        running.append((server, thread))
        host, port = server.server_address[:2]
        mirror = Mirror(f"http://{host}:{port}/{PREFIX}", requests)
        monkeypatch.setenv(URL_VARIABLE, mirror.base)
        monkeypatch.setenv("NO_PROXY", "127.0.0.1")  # a proxy of the machine is not asked
        return mirror

    yield start
    for server, thread in running:
        server.shutdown()
        server.server_close()
        thread.join()


def _lay_out(folder: Path, corrupt: Collection[str]) -> None:
    """Copy the shared files under ``folder`` as OWNER/REPOSITORY/COMMIT/PATH."""
    for name, source in SHARED_FILES.items():
        remote = DATASETS[name]
        target = folder / remote.repository / remote.commit / remote.path
        target.parent.mkdir(parents=True)
        data = bytearray(source.read_bytes())
        if name in corrupt:
            data[len(data) // 2] ^= 0xFF
        target.write_bytes(bytes(data))


def _served_path(name: str) -> str:
    remote = DATASETS[name]
    return f"/{PREFIX}/{remote.repository}/{remote.commit}/{remote.path}"


def _files(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.is_file()] if folder.exists() else []


@needs_shared
def test_the_shared_copies_are_the_pinned_files() -> None:
    for name, path in SHARED_FILES.items():
        assert pooch.file_hash(str(path)) == DATASETS[name].sha256, name


def test_the_files_are_fetched_from_base_owner_repository_commit_path(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv(URL_VARIABLE, raising=False)
    assert [DATASETS[name].url(base_url()) for name in ("s4", "finger")] == [
        "https://raw.githubusercontent.com/jgrizou/bci_thesis/"
        "0d78e22ad5560e34a2b4c132444b86f4fc5468af/s4.mat",
        "https://raw.githubusercontent.com/jgrizou/experiments_thesis/"
        "890ef8b9bd9001adf764ddc6bf122a42b5519124/continuous_particle/move_finger.mat",
    ]
    monkeypatch.setenv(URL_VARIABLE, "https://mirror.example/data/")  # a trailing / or not
    assert DATASETS["s4"].url(base_url()) == (
        "https://mirror.example/data/jgrizou/bci_thesis/"
        "0d78e22ad5560e34a2b4c132444b86f4fc5468af/s4.mat"
    )


@needs_shared
def test_fetch_all_downloads_each_file_once_and_path_prints_it(
    serve: Callable[..., Mirror], cache: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    mirror = serve()
    assert main(["datasets", "fetch", "all"]) == 0
    assert mirror.requests == [_served_path("s4"), _served_path("finger")]
    out = capsys.readouterr().out
    for name, remote in DATASETS.items():
        kept = cache.resolve() / remote.file_name
        assert pooch.file_hash(str(kept)) == remote.sha256
        assert f"{name}: {kept} (GPL-2.0)" in out
    assert sorted(_files(cache)) == sorted(cache.resolve() / d.file_name for d in DATASETS.values())

    assert main(["datasets", "fetch", "all"]) == 0  # intact in the cache: not downloaded again
    assert len(mirror.requests) == 2
    capsys.readouterr()
    assert main(["datasets", "path", "finger"]) == 0
    assert capsys.readouterr().out == f"{cache.resolve() / 'move_finger.mat'}\n"


@needs_shared
def test_a_corrupted_copy_is_refused_by_its_checksum_and_nothing_is_kept(
    serve: Callable[..., Mirror], cache: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    mirror = serve(corrupt={"s4"})
    assert main(["datasets", "fetch", "s4"]) == 1
    err = capsys.readouterr().err
    assert f"s4: the file at {mirror.base}{_served_path('s4')[len(PREFIX) + 1:]}" in err
    assert f"does not have the pinned sha256 {DATASETS['s4'].sha256}" in err
    assert "nothing was kept" in err and "Traceback" not in err
    assert _files(cache) == []
    assert main(["datasets", "path", "s4"]) == 1

    assert main(["datasets", "fetch", "all"]) == 1  # s4 refused again, finger still fetched
    assert "s4: the file at" in capsys.readouterr().err
    assert _files(cache) == [cache.resolve() / "move_finger.mat"]


@needs_shared
def test_a_damaged_cached_file_is_reported_and_fetched_again(
    serve: Callable[..., Mirror], cache: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    mirror = serve()
    kept = fetch("s4")
    kept.write_bytes(kept.read_bytes()[:-10])
    assert main(["datasets", "path", "s4"]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    assert f"{kept} does not have the pinned sha256" in captured.err
    assert "download it again with: cfbci datasets fetch s4" in captured.err
    assert main(["datasets", "fetch", "s4"]) == 0
    assert mirror.requests == [_served_path("s4")] * 2
    assert fetched_path("s4") == kept and pooch.file_hash(str(kept)) == DATASETS["s4"].sha256


def test_path_before_fetch_names_the_fetch_command(
    cache: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["datasets", "path", "finger"]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    assert "finger is not fetched yet" in captured.err
    assert "download it with: cfbci datasets fetch finger" in captured.err


def test_a_file_missing_from_the_mirror_is_a_clear_error(
    serve: Callable[..., Mirror], cache: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    mirror = serve(empty=True)
    assert main(["datasets", "fetch", "finger"]) == 1
    err = capsys.readouterr().err
    assert f"finger: could not download {mirror.base}/jgrizou/experiments_thesis/" in err
    assert "404" in err and "Traceback" not in err
    assert _files(cache) == []


@pytest.mark.parametrize(
    "address", ["file:///srv/mirror", "mirror.example/cfbci", "http://", "gopher://x.example"]
)
def test_a_bad_datasets_url_is_a_clear_error(
    address: str, cache: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setenv(URL_VARIABLE, address)
    assert main(["datasets", "fetch", "s4"]) == 2
    err = capsys.readouterr().err
    assert "CFBCI_DATASETS_URL must be an http, https or ftp address" in err
    assert repr(address) in err and "Traceback" not in err
    assert _files(cache) == []


@needs_shared
def test_the_fetched_files_load_and_drive_a_simulation(
    serve: Callable[..., Mirror], cache: Path, tmp_path: Path
) -> None:
    serve()
    s4 = load_labelled(fetch("s4"), frame="feedback")
    assert s4.features.shape == (1800, 34)
    assert np.bincount(s4.labels).tolist() == [1440, 360]
    finger = load_labelled(fetch("finger"), frame="guidance")
    assert finger.features.shape == (400, 11)
    assert np.bincount(finger.labels).tolist() == [100] * 4

    command = 'cfbci simulate --dataset "$(cfbci datasets path s4)" --seeds 1 --steps 50'
    environment = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}"
                   f"{os.environ.get('PATH', '')}"}
    done = subprocess.run(
        ["bash", "-c", command], cwd=tmp_path, env=environment, capture_output=True,
        text=True, timeout=300, check=False,
    )
    assert done.returncode == 0, done.stderr
    assert "median first target" in done.stdout


def test_version_prints_the_version_in_pyproject(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit:
        main(["--version"])
    assert exit.value.code == 0
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert capsys.readouterr().out == f"{version}\n"
