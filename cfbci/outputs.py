"""Files and folders a command writes: never over an existing one unless told
(``--overwrite``), never through a symbolic link, never half-written.

A file is written under a temporary name in its folder, then given its name: with
``overwrite``, by ``os.replace`` (which replaces a link itself, never the file it points
to); without, by ``os.link``, which fails if the name was taken meanwhile. A folder of
several outputs (a report) is refused when it holds anything, unless ``overwrite``; its
files are written in a temporary folder inside it, then placed one by one as above.
"""

from __future__ import annotations

import os
import secrets
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def refuse_existing(path: Path, overwrite: bool) -> None:
    """A ``FileExistsError`` if ``path`` exists (a dangling link too) and not ``overwrite``;
    an ``IsADirectoryError`` if it is a folder."""
    if path.is_dir() and not path.is_symlink():
        raise IsADirectoryError(f"{path} is a folder; give a file name")
    if os.path.lexists(path) and not overwrite:
        raise FileExistsError(f"{path} exists (--overwrite replaces it)")


def place(written: Path, target: Path, overwrite: bool) -> None:
    """Give the file ``written`` the name ``target`` (same file system): replacing what has
    that name (a link itself, never written through) if ``overwrite``, else only if the
    name is free; ``written`` is left in place when that fails (``FileExistsError``)."""
    if overwrite:
        os.replace(written, target)
        return
    try:
        os.link(written, target)  # fails if ``target`` exists: nothing is replaced
    except FileExistsError:
        raise FileExistsError(f"{target} was created meanwhile; not replaced") from None
    written.unlink()


@contextmanager
def new_file(path: Path, overwrite: bool = False) -> Iterator[Path]:
    """A temporary path in ``path``'s folder to write to (its name ends as ``path``'s, for
    writers that check the ending); given ``path``'s name when the block ends without an
    error (see `place`), removed otherwise.

    Raises
    ------
    FileExistsError
        ``path`` exists and not ``overwrite`` (checked before and after the writing).
    """
    refuse_existing(path, overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    written = path.parent / f".cfbci-{secrets.token_hex(6)}-{path.name}"
    os.close(os.open(written, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))  # umask's mode
    try:
        yield written
        place(written, path, overwrite)
    finally:
        written.unlink(missing_ok=True)


@contextmanager
def new_folder(folder: Path, overwrite: bool = False) -> Iterator[Path]:
    """A temporary folder inside ``folder`` to write the outputs to; each file written
    there is given its name in ``folder`` when the block ends without an error (see
    `place`), and the temporary folder is removed either way.

    Raises
    ------
    FileExistsError
        ``folder`` holds files and not ``overwrite``.
    NotADirectoryError
        ``folder`` is a file, or a link (never written through).
    """
    if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
        kind = "a link" if folder.is_symlink() else "a file"
        raise NotADirectoryError(f"{folder} is {kind}; give a folder")
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:
        raise FileExistsError(f"{folder} holds files (--overwrite replaces those of the same "
                              "name; an empty or new folder is fine)")
    folder.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".cfbci-", dir=folder))
    try:
        yield staging
        for written in sorted(staging.rglob("*")):
            if written.is_file():
                target = folder / written.relative_to(staging)
                target.parent.mkdir(parents=True, exist_ok=True)
                place(written, target, overwrite)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
