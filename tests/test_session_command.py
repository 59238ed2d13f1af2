"""``cfbci session`` never overwrites a file unless told, never writes through a link, and
leaves the rest of the recording's folder alone (real service and source processes over
loopback Zenoh, real MCAP files)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from cfbci.cli import main
from replay.recording import read_recording


def test_an_existing_record_file_is_refused_before_anything_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    record = tmp_path / "existing.mcap"
    record.write_bytes(b"an earlier recording")
    assert main(["session", "--steps", "5", "--record", str(record)]) == 2
    err = capsys.readouterr().err
    assert "exists" in err and "--overwrite" in err
    assert record.read_bytes() == b"an earlier recording"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["existing.mcap"]


def test_overwrite_replaces_the_file_and_a_link_itself_never_its_target(
    tmp_path: Path,
) -> None:
    """With --overwrite the record file is replaced; a record path that is a link is
    replaced by the recording, its target left as it was; another recording of the same
    session id in the folder is untouched."""
    target = tmp_path / "target.bin"
    target.write_bytes(b"not a recording")
    record = tmp_path / "run.mcap"
    os.symlink(target, record)
    neighbour = tmp_path / "run.2.mcap"
    neighbour.write_bytes(b"another file")
    assert main(["session", "--steps", "6", "--seed", "1", "--record", str(record),
                 "--overwrite"]) == 0
    assert not record.is_symlink()
    assert target.read_bytes() == b"not a recording"
    assert neighbour.read_bytes() == b"another file"
    assert len(read_recording(record).messages["/move"]) == 6
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.2.mcap", "run.mcap", "target.bin"]


@pytest.mark.parametrize(
    ("options", "problem"),
    [
        (["--dataset", "typo.mat"], "typo.mat: no such file"),
        (["--grid", "50"], "field 'grid' must be in 2..10; got 50"),
        (["--grid", "7", "--world", "pick-and-place"], "--grid applies to --world grid only"),
        (["--set", "shrinkage=banana"], "a number in [0, 1] or one of 'oas', 'cv'"),
        (["--world", "line", "--frame", "cardinal"], "frame"),
    ],
)
def test_a_bad_input_is_refused_before_anything_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], options: list[str], problem: str
) -> None:
    """One line naming the problem, exit status 2, and nothing started: no board drawn,
    no recording folder made."""
    record = tmp_path / "runs" / "s.mcap"
    assert main(["session", "--steps", "5", "--record", str(record), *options]) == 2
    captured = capsys.readouterr()
    assert problem in captured.err
    assert captured.out == ""  # no live board
    assert not record.parent.exists()


def test_the_embedded_service_takes_the_limits_given(tmp_path: Path) -> None:
    """--max-grid reaches the embedded service: a 12 x 12 grid, over the default limit,
    runs when allowed."""
    record = tmp_path / "big.mcap"
    assert main(["session", "--grid", "12", "--max-grid", "12", "--steps", "3",
                 "--record", str(record)]) == 0
    assert read_recording(record).config["grid"] == 12
