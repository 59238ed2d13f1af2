"""Download the public real data sets the documentation uses, pinned by commit and sha256.

Two files, both from J. Grizou's public thesis repositories on GitHub (GNU GPL v2): the
user's machine downloads them from their source; cfbci never redistributes them.

Where the files come from
    ``BASE/OWNER/REPOSITORY/COMMIT/PATH``: ``BASE`` is
    ``https://raw.githubusercontent.com`` (GitHub's raw files), or the value of the
    environment variable `URL_VARIABLE` (``CFBCI_DATASETS_URL``) for a mirror laid out
    the same way, e.g. ``https://mirror.example/cfbci`` serves
    ``https://mirror.example/cfbci/jgrizou/bci_thesis/0d78.../s4.mat``.
Where they are kept
    The user's cache folder (`pooch.os_cache`, ``~/.cache/cfbci`` on Linux), or the
    folder named by the environment variable `FOLDER_VARIABLE` (``CFBCI_DATA_DIR``).

A download whose sha256 differs from the pinned one is refused and nothing is kept.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from urllib.parse import urlsplit

import pooch

#: Environment variable: base address of a mirror of the files (default GitHub's raw files).
URL_VARIABLE = "CFBCI_DATASETS_URL"
#: Environment variable: folder the fetched files are kept in (default the user's cache).
FOLDER_VARIABLE = "CFBCI_DATA_DIR"
#: Base address of the files' public source.
DEFAULT_URL = "https://raw.githubusercontent.com"
#: The address schemes a base address may have (the ones pooch downloads from).
_SCHEMES = ("http", "https", "ftp")


class FetchError(RuntimeError):
    """A data set could not be downloaded, or is not (intact) in the cache folder."""


@dataclass(frozen=True)
class RemoteDataset:
    """One public file: where it is, which version, and its checksum."""

    name: str  #: short name on the command line
    title: str  #: what the file holds
    repository: str  #: ``OWNER/REPOSITORY`` on GitHub
    commit: str  #: the pinned commit (40 hex digits)
    path: str  #: the file's path in the repository, ``/``-separated
    sha256: str  #: checksum of the pinned file (64 hex digits)
    licence: str  #: SPDX identifier of the file's licence

    @property
    def file_name(self) -> str:
        """The name the file is kept under in the cache folder."""
        return PurePosixPath(self.path).name

    def url(self, base: str) -> str:
        """The file's address under ``base``: ``BASE/OWNER/REPOSITORY/COMMIT/PATH``."""
        return f"{base.rstrip('/')}/{self.repository}/{self.commit}/{self.path}"


#: The data sets ``cfbci datasets fetch`` downloads, by name.
DATASETS: dict[str, RemoteDataset] = {
    d.name: d
    for d in (
        RemoteDataset(
            name="s4",
            title="ErrP features of subject 4 (feedback frame): X 1800 x 34, Y 1 = correct, "
            "2 = error",
            repository="jgrizou/bci_thesis",
            commit="0d78e22ad5560e34a2b4c132444b86f4fc5468af",
            path="s4.mat",
            sha256="58e6ca411e520099f6f7f9f5881ccd4c07063d3a371a563b3ce3eb9dd78200e5",
            licence="GPL-2.0",
        ),
        RemoteDataset(
            name="finger",
            title="finger-movement features (guidance frame): X 400 x 11, Y 1..4",
            repository="jgrizou/experiments_thesis",
            commit="890ef8b9bd9001adf764ddc6bf122a42b5519124",
            path="continuous_particle/move_finger.mat",
            sha256="1d98028aee14e6dbc29cd6d98536b23ab9441f038aa457fc4d7a0acdfdddc1a8",
            licence="GPL-2.0",
        ),
    )
}


def data_folder() -> Path:
    """The folder fetched files are kept in: ``$CFBCI_DATA_DIR``, else the user's cache."""
    chosen = os.environ.get(FOLDER_VARIABLE, "")
    return Path(chosen) if chosen else Path(pooch.os_cache("cfbci"))


def base_url() -> str:
    """The address the files are fetched under: ``$CFBCI_DATASETS_URL``, else GitHub's.

    Raises
    ------
    ValueError
        If the variable is set to something other than an http, https or ftp address.
    """
    chosen = os.environ.get(URL_VARIABLE, "")
    if not chosen:
        return DEFAULT_URL
    parts = urlsplit(chosen)
    if parts.scheme not in _SCHEMES or not parts.netloc:
        raise ValueError(
            f"{URL_VARIABLE} must be an http, https or ftp address such as "
            f"https://mirror.example/cfbci; got {chosen!r}"
        )
    return chosen


def remote_dataset(name: str) -> RemoteDataset:
    """The pinned data set called ``name`` (a key of `DATASETS`)."""
    try:
        return DATASETS[name]
    except KeyError:
        raise ValueError(
            f"unknown data set {name!r}; the data sets are {', '.join(DATASETS)}"
        ) from None


def fetch(name: str, folder: Path | None = None, base: str | None = None) -> Path:
    """Download data set ``name`` into ``folder`` unless an intact copy is already there.

    Parameters
    ----------
    name
        A key of `DATASETS`.
    folder
        Where to keep the file (default `data_folder`).
    base
        Base address, the file at ``BASE/OWNER/REPOSITORY/COMMIT/PATH`` (default
        `base_url`).

    Returns
    -------
    The absolute path of the file, whose sha256 is the pinned one.

    Raises
    ------
    FetchError
        If the download fails, or the downloaded file's sha256 is not the pinned one (the
        file is then not kept).
    """
    remote = remote_dataset(name)
    folder = data_folder() if folder is None else folder
    url = remote.url(base_url() if base is None else base)
    try:
        kept = pooch.retrieve(
            url, known_hash=f"sha256:{remote.sha256}", fname=remote.file_name, path=folder
        )
    except ValueError as error:  # pooch's answer to a checksum mismatch
        raise FetchError(
            f"{name}: the file at {url} does not have the pinned sha256 {remote.sha256}; it "
            f"was refused and nothing was kept (a damaged or different copy: {error})"
        ) from None
    except OSError as error:  # network and HTTP errors (requests' are OSErrors), disk errors
        raise FetchError(f"{name}: could not download {url} into {folder}: {error}") from None
    return Path(kept)


def fetched_path(name: str, folder: Path | None = None) -> Path:
    """The absolute path of data set ``name`` in ``folder`` (default `data_folder`).

    Raises
    ------
    FetchError
        If the file is absent, or its sha256 is not the pinned one; the message names the
        command that downloads it.
    """
    remote = remote_dataset(name)
    path = ((data_folder() if folder is None else folder) / remote.file_name).resolve()
    if not path.is_file():
        raise FetchError(
            f"{name} is not fetched yet (no {path}); download it with: "
            f"cfbci datasets fetch {name}"
        )
    if pooch.file_hash(str(path)) != remote.sha256:
        raise FetchError(
            f"{path} does not have the pinned sha256 {remote.sha256} (damaged or replaced); "
            f"download it again with: cfbci datasets fetch {name}"
        )
    return path
