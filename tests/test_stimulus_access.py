"""The stimulus socket of ``cfbci view --stimulus`` (``/stimulus``), over real HTTP: guarded
as every request to the view, one page at a time the stimulus (the role passed on to the
page refused first when it leaves), pinged for its clock; a view without ``--stimulus``
has no such socket; bad stimulus options are refused with a message. The view runs as the
real command (tests/test_view_security.py's harness), its LSL on the loopback (an
``lsl_api.cfg`` of the test's own); this process calls no liblsl function. The whole loop
in a browser is tests/test_stimulus_loop.py."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from test_view_security import TIMEOUT, RunningView, _websocket, view_command

from acquisition.lsl_streams import loopback_config


@pytest.fixture(scope="module")
def stimulus_view(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningView]:
    folder = tmp_path_factory.mktemp("stimulus-view")
    # The module's fixture may run in each pytest-xdist worker, under the same folder
    # name: the process id keeps their LSL apart.
    (folder / "lsl_api.cfg").write_text(
        loopback_config(f"cfbci-test-{folder.name}-{os.getpid()}"))
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("LSLAPICFG", str(folder / "lsl_api.cfg"))
        with view_command("--stimulus", "--moves", f"moves-{folder.name}", "--onsets",
                          f"onsets-{folder.name}", "--grid", "4", "--target", "5",
                          "--interval", "0.5") as running:
            yield running


def _claims(view: RunningView) -> dict[str, Any]:
    """Two pages claim the stimulus; the first answers three pings; then it leaves, and the
    second, refused before, is given the role. What each was told."""

    async def run() -> dict[str, Any]:
        url = f"{view.base}/stimulus?token={view.token}"
        told: dict[str, Any] = {}
        async with aiohttp.ClientSession() as client:
            first = await client.ws_connect(url)
            await first.send_json({"type": "stimulus"})
            told["first"] = await first.receive_json(timeout=TIMEOUT)
            second = await client.ws_connect(url)
            await second.send_json({"type": "stimulus"})
            told["second"] = await second.receive_json(timeout=TIMEOUT)
            pings = []
            while len(pings) < 3:
                message = await first.receive_json(timeout=TIMEOUT)
                pings.append(message)
                await first.send_json({"type": "pong", "id": message["id"], "page_ms": 1.0})
            told["pings"] = pings
            await first.close()
            told["second again"] = await second.receive_json(timeout=TIMEOUT)
            await second.close()
        return told

    return asyncio.run(asyncio.wait_for(run(), TIMEOUT))


def test_one_page_at_a_time_is_the_stimulus_and_is_pinged(stimulus_view: RunningView) -> None:
    told = _claims(stimulus_view)
    settings = {"interval_ms": 500.0, "grid": 4, "fixation": True, "target": 5,
                "frame_tolerance": 1.5}
    assert told["first"] == {"type": "stimulus", "settings": settings}
    assert told["second"] == {"type": "stimulus", "refused": "another page is the stimulus"}
    assert [p["type"] for p in told["pings"]] == ["ping"] * 3
    ids = [p["id"] for p in told["pings"]]
    assert ids == sorted(set(ids))
    assert told["second again"] == {"type": "stimulus", "settings": settings}


def test_the_stimulus_socket_is_guarded_as_the_view(stimulus_view: RunningView) -> None:
    base = stimulus_view.base
    assert _websocket(f"{base}/stimulus")[0] == 403
    assert _websocket(f"{base}/stimulus?token={stimulus_view.token}",
                      origin="http://attacker.test")[0] == 403
    assert _websocket(f"{base}/stimulus?token={stimulus_view.token}",
                      Host="rebound.test")[0] == 403


def test_a_view_without_stimulus_has_no_stimulus_socket() -> None:
    with view_command() as view:
        assert _websocket(f"{view.base}/stimulus?token={view.token}")[0] == 404


@pytest.mark.parametrize(("options", "message"), [
    (["--target", "25"], "--target must be a cell of the 5x5 grid, 0..24; got 25"),
    (["--interval", "-1"], "--interval must be at least 0 s; got -1.0"),
    (["--frame-tolerance", "1"], "--frame-tolerance must be above 1 refresh period"),
])
def test_bad_stimulus_options_are_refused_with_a_message(
    options: list[str], message: str, tmp_path: Path
) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "cfbci.cli", "view", "--connect", "tcp/127.0.0.1:1",
         "--stimulus", *options], capture_output=True, text=True, timeout=TIMEOUT,
        cwd=tmp_path,
    )
    assert result.returncode != 0
    assert message in result.stderr and "Traceback" not in result.stderr


@pytest.mark.parametrize(("options", "message"), [
    (["--onsets", "m", "--drop", "2:0:5"], "do not go with --onsets"),
    (["--onsets", "m", "--marker-latency", "0"], "--marker-latency must be positive; got 0.0"),
])
def test_bad_listening_options_are_refused_with_a_message(
    options: list[str], message: str, tmp_path: Path
) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "cfbci.cli", "lsl-simulator", "--session", "s", "--connect",
         "tcp/127.0.0.1:1", *options], capture_output=True, text=True, timeout=TIMEOUT,
        cwd=tmp_path,
    )
    assert result.returncode != 0
    assert message in result.stderr and "Traceback" not in result.stderr
