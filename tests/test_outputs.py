"""``recover``, ``report`` and ``export`` never replace an existing file unless told
(``--overwrite``), never write through a symbolic link, and an existing empty output folder
is fine (a real recording: the reference grid session of raw epochs)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from cfbci.cli import main
from replay.recording import read_recording

RECORDING = Path(__file__).resolve().parent / "behaviour" / "reference" / "session-grid.mcap"


@pytest.fixture
def recording(tmp_path: Path) -> Path:
    return Path(shutil.copy(RECORDING, tmp_path / "s.mcap"))


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    status = main(argv)
    captured = capsys.readouterr()
    return status, (captured.out + captured.err).replace("\n", " ")


@pytest.mark.parametrize(("command", "default"), [("recover", "s.recovered.mcap"),
                                                  ("export", "s-epo.fif")])
def test_an_existing_output_file_is_refused_unless_overwrite(
    recording: Path, command: str, default: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """Was: ``cfbci recover`` replaced an existing ``<stem>.recovered.mcap``."""
    existing = recording.with_name(default)
    existing.write_text("an earlier output")
    status, out = run([command, str(recording)], capsys)
    assert status == 2 and f"{existing} exists (--overwrite replaces it)" in out, out
    assert existing.read_text() == "an earlier output"
    assert sorted(p.name for p in recording.parent.iterdir()) == sorted(["s.mcap", default])

    status, out = run([command, str(recording), "--overwrite"], capsys)
    assert status == 0, out
    assert existing.read_bytes() != b"an earlier output"
    if command == "recover":
        assert read_recording(existing).complete


@pytest.mark.parametrize(("command", "name"), [("recover", "copy.mcap"),
                                               ("export", "copy-epo.fif")])
def test_a_link_is_never_written_through(
    recording: Path, tmp_path: Path, command: str, name: str,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Was: ``cfbci recover --out LINK`` wrote into the link's target."""
    target = tmp_path / "elsewhere.txt"
    target.write_text("someone else's file")
    link = tmp_path / name
    link.symlink_to(target)
    status, out = run([command, str(recording), "--out", str(link)], capsys)
    assert status == 2 and "exists (--overwrite replaces it)" in out, out
    status, out = run([command, str(recording), "--out", str(link), "--overwrite"], capsys)
    assert status == 0, out
    assert target.read_text() == "someone else's file"
    assert not link.is_symlink() and link.stat().st_size > 1000  # the link itself replaced

    dangling = tmp_path / f"dangling-{name}"
    dangling.symlink_to(tmp_path / "nowhere" / "x")
    status, out = run([command, str(recording), "--out", str(dangling)], capsys)
    assert status == 2 and "exists" in out and not (tmp_path / "nowhere").exists()


def test_a_report_into_a_folder_holding_files_is_refused_unless_overwrite(
    recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Was: ``cfbci report --out DIR`` replaced DIR's ``index.html`` and ``metrics.json``."""
    out_dir = tmp_path / "report"
    out_dir.mkdir()  # an existing empty folder is fine
    status, out = run(["report", str(recording), "--out", str(out_dir), "--jobs", "1"], capsys)
    assert status == 0, out
    written = {p.name: p.read_bytes() for p in out_dir.iterdir()}
    assert "index.html" in written and "metrics.json" in written
    assert not [p for p in out_dir.iterdir() if p.name.startswith(".")]  # no staging left

    notes = out_dir / "notes.txt"
    notes.write_text("mine")
    status, out = run(["report", str(recording), "--out", str(out_dir), "--jobs", "1"], capsys)
    assert status == 2 and f"{out_dir} holds files" in out, out
    assert {p.name: p.read_bytes() for p in out_dir.iterdir() if p != notes} == written

    target = tmp_path / "elsewhere.html"
    target.write_text("someone else's page")
    (out_dir / "index.html").unlink()
    (out_dir / "index.html").symlink_to(target)
    status, out = run(["report", str(recording), "--out", str(out_dir), "--jobs", "1",
                       "--overwrite"], capsys)
    assert status == 0, out
    assert target.read_text() == "someone else's page" and notes.read_text() == "mine"
    assert not (out_dir / "index.html").is_symlink()
    assert "<html" in (out_dir / "index.html").read_text()


def test_a_report_folder_that_is_a_link_or_a_file_is_refused(
    recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    real = tmp_path / "real"
    real.mkdir()
    (tmp_path / "linked").symlink_to(real)
    status, out = run(["report", str(recording), "--out", str(tmp_path / "linked")], capsys)
    assert status == 2 and "is a link; give a folder" in out, out
    (tmp_path / "file").write_text("x")
    status, out = run(["report", str(recording), "--out", str(tmp_path / "file")], capsys)
    assert status == 2 and "is a file; give a folder" in out, out
    assert list(real.iterdir()) == []


def test_what_the_readme_and_docs_write_in_a_clone_is_ignored_by_git() -> None:
    """Was: ``report/`` (the tour's report) and ``lsl_api.cfg`` (the LSL pages' loopback
    configuration) showed as untracked files after following the docs."""
    ignored = set((Path(__file__).resolve().parents[1] / ".gitignore").read_text().split())
    assert {"runs/", "report/", "lsl_api.cfg", "*.mcap", "site/"} <= ignored
