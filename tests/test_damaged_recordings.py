"""Damaged recordings are read for what they hold, and said to be damaged.

A real recording (``cfbci session``, synthetic raw epochs) cut anywhere, cut with garbage
after it, or with one bit flipped: ``cfbci replay`` compares its whole steps and says where
the file ends (exit 3, never a false divergence at the cut), ``cfbci report`` reports it
(also cut between a step's ``/epoch`` and ``/features``), ``cfbci recover`` keeps every
intact chunk around a damaged one and says what it dropped, ``cfbci export`` exports what
it holds; no traceback, and the input is never modified.
"""

from __future__ import annotations

import hashlib
import json
import random
import subprocess
import sys
from itertools import pairwise
from pathlib import Path

import pytest
from mcap.reader import make_reader

from cfbci.cli import main
from replay.recording import read_recording

ROOT = Path(__file__).resolve().parents[1]
STEPS = 40


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A live ``cfbci session`` of 40 steps on a 3 x 3 grid (synthetic raw epochs)."""
    path = tmp_path_factory.mktemp("recorded") / "session.mcap"
    done = subprocess.run(
        [sys.executable, "-m", "cfbci.cli", "session", "--steps", str(STEPS), "--seed", "3",
         "--grid", "3", "--record", str(path)],
        capture_output=True, text=True, cwd=ROOT, timeout=300,
    )
    assert done.returncode == 0, done.stderr
    return path


def chunks(path: Path) -> list[tuple[int, int, str]]:
    """(start, end, topic) of every chunk (one message each), through the file's index."""
    with path.open("rb") as file:
        summary = make_reader(file).get_summary()
    assert summary is not None
    topics = {c.id: c.topic for c in summary.channels.values()}
    found = []
    for index in summary.chunk_indexes:
        [channel] = index.message_index_offsets or [None]
        found.append((index.chunk_start_offset, index.chunk_start_offset + index.chunk_length,
                      topics.get(channel, "")))
    return found


def ends_after(path: Path, topic: str, before: str) -> list[int]:
    """Offsets just past a ``topic`` chunk followed by a ``before`` chunk, truths aside (a
    source's truth is recorded whenever it comes: between a move and its state, say)
    (message indexes included: where a writer killed between the two leaves the file)."""
    found = chunks(path)
    kept = [k for k, (_, _, topic_k) in enumerate(found) if topic_k != "/truth"]
    return [found[k + 1][0] for k, n in pairwise(kept)
            if found[k][2] == topic and found[n][2] == before]


def cut(source: Path, target: Path, at: int, tail: bytes = b"") -> Path:
    target.write_bytes(source.read_bytes()[:at] + tail)
    return target


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    status = main(argv)
    captured = capsys.readouterr()
    return status, captured.out.replace("\n", " "), captured.err.replace("\n", " ")


def test_the_recording_replays_identically_and_complete(
    recorded: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    status, out, _ = run(["replay", str(recorded)], capsys)
    assert status == 0 and f"identical: {STEPS} moves, {STEPS + 1} states" in out
    assert "truncated" not in out and "damaged" not in out


def test_replay_of_a_recording_cut_in_half_says_so_and_exits_3(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    half = cut(recorded, tmp_path / "half.mcap", recorded.stat().st_size // 2)
    before = digest(half)
    status, out, _ = run(["replay", str(half), "--json", str(tmp_path / "r.json")], capsys)
    assert status == 3, out
    assert "identical as far as the file goes" in out and "truncated at byte" in out
    assert "have no epoch in the file" in out
    written = json.loads((tmp_path / "r.json").read_text())
    assert written["status"] == 3 and written["identical"] and not written["complete"]
    assert "truncated at byte" in written["warning"] and written["steps_configured"] == STEPS
    assert 0 < written["steps_compared"] < STEPS
    assert digest(half) == before


@pytest.mark.parametrize(("topic", "following"), [
    ("/features", "/move"),  # after an accepted epoch, before its move
    ("/move", "/state"),  # between a move and its state
    ("/epoch", "/features"),  # between an epoch and its features (a SIGKILL can leave it)
    ("/state", "/belief"),
])
def test_replay_never_diverges_at_a_cut_between_a_steps_messages(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], topic: str,
    following: str,
) -> None:
    """Cut between two messages of a step: the whole steps are compared, the cut one only
    in what the file holds (said), exit 3, never a 'count' divergence."""
    offsets = ends_after(recorded, topic, following)
    assert len(offsets) >= STEPS // 2
    for at in offsets[:: max(1, len(offsets) // 6)]:
        path = cut(recorded, tmp_path / "cut.mcap", at)
        status, out, err = run(["replay", str(path)], capsys)
        assert status == 3, (at, out, err)
        assert "first divergence" not in out and "truncated at byte" in out, (at, out)


def test_report_of_a_recording_cut_between_an_epoch_and_its_features(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """What a SIGKILL can leave: the report reports it (was: 'x and y must have same first
    dimension'), and so after ``cfbci recover``."""
    at = ends_after(recorded, "/epoch", "/features")[STEPS // 2]
    path = cut(recorded, tmp_path / "killed.mcap", at)
    status, out, err = run(["report", str(path), "--out", str(tmp_path / "report"),
                            "--jobs", "1"], capsys)
    assert status == 0, err
    [session] = json.loads((tmp_path / "report" / "metrics.json").read_text())["sessions"]
    assert session["truncated"] and "truncated at byte" in session["warning"]
    assert session["replay_identical"] is True
    # the epoch of step 21 cut before its features: 20 epochs observed
    assert session["n_signals"] == len(session["accuracy_truth"]) == STEPS // 2
    assert "truncated recording" in out

    clean = tmp_path / "recovered.mcap"
    assert run(["recover", str(path), "--out", str(clean)], capsys)[0] == 0
    status, _, err = run(["report", str(clean), "--out", str(tmp_path / "again"),
                          "--jobs", "1"], capsys)
    assert status == 0, err
    [again] = json.loads((tmp_path / "again" / "metrics.json").read_text())["sessions"]
    assert again["n_signals"] == len(again["accuracy_truth"]) == session["n_signals"]


def test_a_cut_file_with_garbage_after_it_is_no_traceback(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Was an uncaught OverflowError (a huge record length) in replay and recover."""
    garbage = b"\xff" * 64 + bytes(range(256)) * 8
    size = recorded.stat().st_size
    boundary = chunks(recorded)[len(chunks(recorded)) // 2][0]  # a chunk's first byte
    # first: cut in a chunk's header, just before its records' length, which the garbage
    # makes 2**64 - 1 (was the OverflowError); then garbage after a record and anywhere
    for at, tail in ((boundary + 9 + 32, garbage), (boundary, b"\x06" + garbage),
                     (int(size * 0.3), garbage), (int(size * 0.6), garbage)):
        path = cut(recorded, tmp_path / f"garbage-{at}.mcap", at, tail)
        before = digest(path)
        status, out, _ = run(["replay", str(path)], capsys)
        assert status == 3 and "identical as far as the file goes" in out, out
        assert "truncated at byte" in out or "damaged" in out
        clean = tmp_path / f"recovered-{at}.mcap"
        status, out, _ = run(["recover", str(path), "--out", str(clean)], capsys)
        assert status in (0, 3) and "recovered" in out
        assert read_recording(clean).complete
        assert digest(path) == before
    done = subprocess.run([sys.executable, "-m", "cfbci.cli", "replay", str(path)],
                          capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert done.returncode == 3 and "Traceback" not in done.stderr, done.stderr


def test_recover_keeps_every_intact_chunk_around_a_flipped_bit(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Was 'crc validation failed' for the whole file: now the one damaged chunk is
    dropped (said, with its byte range) and every other message kept."""
    whole = read_recording(recorded)
    found = chunks(recorded)
    start, end, _ = next(c for c in found[len(found) // 2:] if c[2] == "/belief")
    data = bytearray(recorded.read_bytes())
    data[(start + end) // 2] ^= 0x10
    path = tmp_path / "flipped.mcap"
    path.write_bytes(bytes(data))
    before = digest(path)
    clean = tmp_path / "clean.mcap"
    status, out, _ = run(["recover", str(path), "--out", str(clean)], capsys)
    assert status == 3
    assert f"damaged: bytes {start}-" in out and "crc mismatch" in out and "/belief" in out
    assert f"recovered {whole.n_messages - 1} messages" in out
    recovered = read_recording(clean)
    assert recovered.complete
    for name, messages in whole.messages.items():
        kept = recovered.messages[name]
        assert kept == messages if name != "/belief" else len(kept) == len(messages) - 1
    assert digest(path) == before

    # A lost belief breaks no step: replay compares every step, and says the file is damaged.
    status, out, _ = run(["replay", str(path)], capsys)
    assert status == 3 and f"{STEPS} moves, {STEPS + 1} states" in out, out
    assert "the steps go on past it" in out
    # Export exports every epoch (none was lost), saying the file is damaged.
    status, out, _ = run(["export", str(path), "--out", str(tmp_path / "x-epo.fif")], capsys)
    assert status == 3 and f"exported {STEPS} epochs" in out and "input damaged" in out
    assert digest(path) == before


def test_a_damaged_length_field_is_skipped_by_scanning_to_the_next_chunk(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    whole = read_recording(recorded)
    found = chunks(recorded)
    start = next(c for c in found[len(found) // 3:] if c[2] == "/epoch")[0]
    data = bytearray(recorded.read_bytes())
    data[start + 4] ^= 0x01  # a high byte of the chunk's record length
    path = tmp_path / "length.mcap"
    path.write_bytes(bytes(data))
    status, out, _ = run(["recover", str(path), "--out", str(tmp_path / "c.mcap")], capsys)
    assert status == 3 and f"damaged: bytes {start}-" in out, out
    assert f"recovered {whole.n_messages - 1} messages" in out
    # The epoch of a step is lost: replay compares the steps before it, and says why.
    status, out, _ = run(["replay", str(path), "--json", str(tmp_path / "r.json")], capsys)
    assert status == 3, out
    written = json.loads((tmp_path / "r.json").read_text())
    assert written["damage"][0]["start"] == start and 0 < written["steps_compared"] < STEPS
    assert any("the usable steps end at byte" in note for note in written["notes"])


def test_the_report_calls_a_file_whose_damage_ends_its_steps_damaged_not_cut(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A lost epoch ends the usable steps: the HTML report says the file is damaged there
    (was: 'Truncated recording (its writer did not close it)', though the writer had)."""
    found = chunks(recorded)
    start = next(c for c in found[len(found) // 3:] if c[2] == "/epoch")[0]
    data = bytearray(recorded.read_bytes())
    data[start + 4] ^= 0x01
    path = tmp_path / "damaged.mcap"
    path.write_bytes(bytes(data))
    out_dir = tmp_path / "report"
    status, _, _ = run(["report", str(path), "--out", str(out_dir), "--jobs", "1"],
                       capsys)
    assert status == 3  # every file reported, some damaged
    page = (out_dir / "index.html").read_text()
    assert "did not close" not in page and "Truncated" not in page
    assert "Damaged recording" in page and f"the usable steps end at byte {start}" in page
    assert "1 damaged" in page
    [session] = json.loads((out_dir / "metrics.json").read_text())["sessions"]
    assert session["damage"]["stop"] == start


def test_an_output_never_overwrites_the_input(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "s.mcap"
    path.write_bytes(recorded.read_bytes())
    before = digest(path)
    for argv in (["replay", str(path), "--json", str(path)],
                 ["recover", str(path), "--out", str(path)],
                 ["export", str(path), "--out", str(path)]):
        status, _, err = run(argv, capsys)
        assert status == 2 and "input" in err, (argv, err)
    assert digest(path) == before


def test_every_flipped_bit_is_found(recorded: Path) -> None:
    """One flipped bit anywhere fails a check (docs/recordings.md): every third byte of
    the magic, header, metadata and first chunk's header, of the file's last 200 bytes
    (summary, footer, magic), and 200 random bytes."""
    from replay.damage import scan_mcap

    data = recorded.read_bytes()
    whole = scan_mcap(data)
    assert whole.intact and not whole.damage
    rng = random.Random(5)
    first_chunk = chunks(recorded)[0][0]
    spots = [*range(0, first_chunk + 64, 3), *(rng.randrange(len(data)) for _ in range(200)),
             *range(len(data) - 200, len(data), 3)]
    for at in spots:
        mutant = bytearray(data)
        mutant[at] ^= 1 << (at % 8)
        scan = scan_mcap(bytes(mutant))
        assert scan.damage, at
        assert len(scan.records) >= len(whole.records) - 20, at  # at most the first chunk
