"""The live view (``cfbci view``) in a real headless browser: Debian's Chromium driven by
Selenium through chromedriver, fed by a real service and source over Zenoh on loopback.

The view runs in a spawned process listening on its own Zenoh endpoint; the services
(one for the module, one more that records the session the re-publishing test sends
again) connect to it and the sources connect to both, as ``cfbci view --listen`` is used.
Every page is opened with the view's access token (`TOKEN`), as from the address
``cfbci view`` prints. The pages tell what they show in ``data-*`` attributes of ``#view``
(session, status, step, agent, layout, correct, wrong, best), which the tests compare with
the messages the service published. Chromium resolves every ``*.test`` name to 127.0.0.1:
a page of another site (``attacker.test``, served by a plain HTTP server of the test) and a
rebound name of the view's own address are then real to the browser. Without Chromium the
tests fail (CI installs it). The last tests check the view's bookkeeping
(`cfbci.view.model`) on real encoded messages; tests/test_view_security.py checks the
access rules over HTTP and the model's refusal of malformed messages.
"""

from __future__ import annotations

import json
import queue
import threading
import time
import urllib.parse
import urllib.request
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from html.parser import HTMLParser
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from live import SPAWN, TIMEOUT, service_process
from matplotlib.image import imread
from selenium import webdriver
from selenium.webdriver.chrome.service import Service as DriverService
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import Select, WebDriverWait
from system_deps import require

from acquisition.simulated_source import SourceSettings, SourceSummary, run_source
from cfbci.recordings.publish import publish_recording
from cfbci.view.checks import layout_of
from cfbci.view.chromium import headless_options
from cfbci.view.model import SessionBook, SessionView
from cfbci.view.server import STATIC, Access, run_view
from replay.recording import read_recording
from wire import protocol
from wire.transport import Outbox, Pump, Received
from wire.zenoh_config import free_tcp_endpoint, peer_config

WINDOW = (1440, 900)  # browser window, CSS pixels
TOKEN = "view-test-token-0123456789"  # the views' access token
SEED = 3  # reaches targets early on the synthetic default (checked below: >= 1 target)
STEPS = 120
POLL = 0.02  # seconds between two readings of a page


def _executable(name: str, debian_path: str) -> str:
    """Debian's chromium or chromium-driver (skips, or fails in CI, when absent)."""
    return require(name, {"chromium": "chromium"}.get(name, "chromium-driver"), debian_path)


def _view_process(listen: str, connect: list[str], access: Access, ready: Any) -> None:
    run_view([listen], connect, access=access, host="127.0.0.1", port=0, on_ready=ready.put)


@contextmanager
def _view_running(
    connect: tuple[str, ...] = (), allow_origins: tuple[str, ...] = ()
) -> Iterator[tuple[str, str]]:
    """A view in a spawned process, its token `TOKEN`: (its address without the
    token, e.g. ``http://127.0.0.1:8080``, its Zenoh endpoint)."""
    endpoint = free_tcp_endpoint()
    ready = SPAWN.Queue()
    access = Access(TOKEN, allow_origins=allow_origins)
    process = SPAWN.Process(target=_view_process,
                            args=(endpoint, list(connect), access, ready))
    process.start()
    try:
        yield ready.get(timeout=TIMEOUT), endpoint
    finally:
        process.terminate()  # SIGTERM: the view stops cleanly
        process.join(TIMEOUT)
        if process.is_alive():
            process.kill()
            process.join()
    assert process.exitcode == 0


class _OtherSite(BaseHTTPRequestHandler):
    """A page of another site that opens the view's WebSocket (the token in hand, as if it
    had leaked) and shows in its title whether the view let it."""

    def do_GET(self) -> None:
        target = self.path.removeprefix("/?ws=")
        page = f"""<!DOCTYPE html><title>connecting</title><script>
const socket = new WebSocket({json.dumps(urllib.parse.unquote(target))});
socket.onopen = () => {{ document.title = "open"; }};
socket.onclose = () => {{ if (document.title !== "open") document.title = "refused"; }};
</script>""".encode()
        self.send_response(200)
        self.send_header("Content-Type", "text/html")
        self.send_header("Content-Length", str(len(page)))
        self.end_headers()
        self.wfile.write(page)

    def log_message(self, *_: Any) -> None:  # quiet
        pass


@pytest.fixture(scope="module")
def other_site() -> Iterator[int]:
    """A plain HTTP server of pages of another site (`_OtherSite`): its port.
    ``friend.test`` on that port is an origin the view allows, ``attacker.test`` not."""
    server = ThreadingHTTPServer(("127.0.0.1", 0), _OtherSite)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield server.server_address[1]
    finally:
        server.shutdown()
        thread.join()
        server.server_close()


@pytest.fixture(scope="module")
def view(other_site: int) -> Iterator[tuple[str, str]]:
    """The view the tests' services connect to; it allows the origin
    ``http://friend.test:<other_site>``."""
    with _view_running(allow_origins=(f"http://friend.test:{other_site}",)) as running:
        yield running


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory) -> Iterator[webdriver.Chrome]:
    """Headless Chromium with a fresh profile."""
    options = headless_options(
        _executable("chromium", "/usr/bin/chromium"), tmp_path_factory.mktemp("chromium-profile"),
        "--host-resolver-rules=MAP *.test 127.0.0.1", f"--window-size={WINDOW[0]},{WINDOW[1]}",
    )
    driver = webdriver.Chrome(
        options=options, service=DriverService(_executable("chromedriver", "/usr/bin/chromedriver"))
    )
    try:
        yield driver
    finally:
        driver.quit()


@pytest.fixture(scope="module")
def service(view: tuple[str, str], tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A service connected to the view; its endpoint, once it answers (see
    `_wait_for_service`). The tests' sessions have ids of their own."""
    endpoint = free_tcp_endpoint()
    with service_process(endpoint, tmp_path_factory.mktemp("recordings"), connect=(view[1],)):
        _wait_for_service(endpoint)
        yield endpoint


@pytest.fixture(scope="module")
def sources() -> Iterator[ProcessPoolExecutor]:
    """Spawned processes to run sources in (two sessions at once)."""
    with ProcessPoolExecutor(2, mp_context=SPAWN) as pool:
        yield pool


def _wait_for_service(endpoint: str) -> None:
    """Publish epochs of an unknown session until the service answers with an error event.

    The view subscribes to configs too, so a source's wait for a config subscriber does not
    tell that the service is up; only the service answers an epoch.
    """
    with zenoh.open(peer_config((), [endpoint])) as session:
        inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
        pump = Pump(session, protocol.key("ping", "event"), "event", inbox)
        outbox = Outbox(session)
        try:
            for _ in range(int(TIMEOUT / 0.25)):
                outbox.send("epoch", "ping", {"step": 1, "signal": "features"},
                            np.zeros(2, np.float32))
                try:
                    inbox.get(timeout=0.25)
                    return
                except queue.Empty:
                    continue
            raise TimeoutError(f"the service on {endpoint} did not answer")
        finally:
            pump.close()
            outbox.close()


class Published:
    """The moves and states of some sessions, as the service published them."""

    def __init__(self, endpoint: str, sessions: tuple[str, ...]) -> None:
        self._inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
        self._zenoh = zenoh.open(peer_config((), [endpoint]))
        self._pumps = [
            Pump(self._zenoh, protocol.key(sid, kind), kind, self._inbox)
            for sid in sessions for kind in ("move", "state")
        ]
        self.moves: dict[str, dict[int, dict[str, Any]]] = {sid: {} for sid in sessions}
        self.last_state: dict[str, protocol.Message] = {}

    def collect(self) -> Published:
        """Take in what has arrived."""
        while not self._inbox.empty():
            received = self._inbox.get()
            message = protocol.decode(received.data, key_expr=received.key_expr)
            if message.kind == "move":
                self.moves[message.session][message.fields["step"]] = message.fields
            else:
                self.last_state[message.session] = message
        return self

    def wait_for_move(self, session: str, step: int) -> None:
        """Wait until the move of ``step`` has arrived."""
        while step not in self.moves[session]:
            received = self._inbox.get(timeout=TIMEOUT)
            message = protocol.decode(received.data, key_expr=received.key_expr)
            if message.kind == "move":
                self.moves[message.session][message.fields["step"]] = message.fields

    def close(self) -> None:
        for pump in self._pumps:
            pump.close()
        self._zenoh.close()


def _start_sources(
    pool: ProcessPoolExecutor, settings: list[SourceSettings], endpoints: list[str]
) -> list[Future[SourceSummary]]:
    return [pool.submit(run_source, s, [], endpoints) for s in settings]


def _shown(browser: webdriver.Chrome) -> dict[str, str]:
    """The data-* attributes of the page's #view, read at once."""
    return browser.execute_script(
        "return Object.assign({}, document.getElementById('view').dataset)"
    )


def _wait(
    browser: webdriver.Chrome, condition: Callable[[dict[str, str]], bool], what: str,
    seen: list[dict[str, str]] | None = None,
) -> dict[str, str]:
    """Poll the page's attributes until ``condition`` holds (every reading kept in ``seen``).

    Fails when the page has shown nothing new for ``TIMEOUT`` seconds (a loaded machine
    makes sessions slow, not stuck).
    """
    last: dict[str, str] = {}
    deadline = time.monotonic() + TIMEOUT
    while True:
        shown = _shown(browser)
        if seen is not None:
            seen.append(shown)
        if condition(shown):
            return shown
        if shown != last:
            last, deadline = shown, time.monotonic() + TIMEOUT
        elif time.monotonic() > deadline:
            pytest.fail(f"the page never showed {what}; last shown: {last}")
        time.sleep(POLL)


def _ended(sid: str, steps: int) -> Callable[[dict[str, str]], bool]:
    return lambda shown: (
        shown.get("session") == sid and shown.get("status") == "ended"
        and shown.get("step") == str(steps)
    )


def _check_png(path: Path) -> None:
    image = imread(path)
    assert image.shape[1] == WINDOW[0] and image.shape[0] >= WINDOW[1] // 2, image.shape
    colours = np.unique((image[..., :3] * 255).astype(np.uint8).reshape(-1, 3), axis=0)
    assert len(colours) > 50, f"{path}: only {len(colours)} colours, a blank page?"


@dataclass
class Followed:
    """A session a page followed: every reading of its attributes, the last one, the
    source's summary, and what the service published."""

    seen: list[dict[str, str]]
    final: dict[str, str]
    summary: SourceSummary
    moves: dict[int, dict[str, Any]]
    last_state: protocol.Message


def _follow(
    browser: webdriver.Chrome, page: str, settings: SourceSettings, service: str,
    view_endpoint: str, sources: ProcessPoolExecutor, shows_beliefs: bool = True,
) -> Followed:
    """Open ``page`` (which names the session), then run the session while reading it; a
    page that ``shows_beliefs`` is read until it shows the last state's best task."""
    sid = settings.session
    browser.get(page)
    _wait(browser, lambda shown: shown.get("session") == sid, "the session it was asked for")
    published = Published(service, (sid,))
    try:
        [future] = _start_sources(sources, [settings], [service, view_endpoint])
        seen: list[dict[str, str]] = []
        final = _wait(browser, _ended(sid, settings.steps), f"the end of {sid}", seen)
        summary = future.result()  # the source's own timeout guards it
        published.collect()
        # The last state and the end event travel on different keys: the page may show the
        # end before the last state; wait for the state too.
        best = str(published.last_state[sid].fields["best_task"])
        if shows_beliefs:
            final = _wait(
                browser, lambda shown: _ended(sid, settings.steps)(shown)
                and shown.get("best") == best, f"the final state of {sid} (best {best})", seen,
            )
    finally:
        published.close()
    return Followed(seen, final, summary, published.moves[sid], published.last_state[sid])


def _shown_steps(followed: Followed) -> dict[int, str]:
    """Step -> agent cell, as the page showed them (steps >= 1), checked against the
    service's moves: the agent shown at a step is where the move of that step put it."""
    sid = followed.summary.session
    shown = {int(s["step"]): s["agent"] for s in followed.seen
             if s["session"] == sid and int(s["step"]) > 0}
    for step, agent in shown.items():
        assert agent == str(followed.moves[step]["to_state"]), f"step {step}"
    return shown


def test_operator_view_follows_a_live_session(
    view: tuple[str, str], browser: webdriver.Chrome, service: str,
    sources: ProcessPoolExecutor, tmp_path: Path,
) -> None:
    url, view_endpoint = view
    settings = SourceSettings("live", seed=SEED, steps=STEPS, interval=0.03)
    followed = _follow(browser, f"{url}/?session=live&token={TOKEN}", settings, service,
                       view_endpoint, sources)
    final, summary = followed.final, followed.summary
    assert sorted(followed.moves) == list(range(1, STEPS + 1))
    # Followed as it ran: many intermediate steps shown, each matching the service's move.
    assert len(_shown_steps(followed)) >= STEPS // 4
    assert final["agent"] == str(followed.moves[STEPS]["to_state"])
    assert final["layout"] == "grid"
    # Targets: as many correct and wrong ones as the source counted from the truth.
    assert summary.correct_targets >= 1
    assert (final["correct"], final["wrong"]) == (
        str(summary.correct_targets), str(summary.wrong_targets)
    )
    # The heat map and the ranking show the final state's beliefs.
    best = str(followed.last_state.fields["best_task"])
    assert final["best"] == best
    cells = browser.find_elements(By.CSS_SELECTOR, "#world rect.cell")
    assert len(cells) == 25
    assert len({cell.value_of_css_property("fill") for cell in cells}) > 1  # a heat map
    assert browser.find_element(By.CSS_SELECTOR, "#ranking li").get_attribute("data-task") == best
    assert browser.find_elements(By.CSS_SELECTOR, "#events li")
    screenshot = tmp_path / "operator-view.png"
    assert browser.save_screenshot(str(screenshot))
    _check_png(screenshot)


def test_subject_view_shows_the_grid_and_the_agent_only(
    view: tuple[str, str], browser: webdriver.Chrome, service: str,
    sources: ProcessPoolExecutor, tmp_path: Path,
) -> None:
    url, view_endpoint = view
    settings = SourceSettings("subject", seed=1, steps=30, interval=0.03)
    followed = _follow(
        browser, f"{url}/subject?session=subject&token={TOKEN}", settings, service,
        view_endpoint, sources,
        shows_beliefs=False,
    )
    assert len(_shown_steps(followed)) >= 30 // 4
    assert followed.final["agent"] == str(followed.moves[30]["to_state"])
    cells = browser.find_elements(By.CSS_SELECTOR, "#world rect.cell")
    assert len(cells) == 25
    assert len({cell.value_of_css_property("fill") for cell in cells}) == 1  # no heat map
    for hidden in (".best", ".truth", ".path", "header", "#ranking", "canvas"):
        assert browser.find_elements(By.CSS_SELECTOR, hidden) == [], hidden
    assert len(browser.find_elements(By.CSS_SELECTOR, "#world circle.agent")) == 1
    grid = browser.find_element(By.CSS_SELECTOR, "#world svg").rect
    viewport = browser.execute_script("return [innerWidth, innerHeight]")
    assert min(grid["width"], grid["height"]) >= 0.9 * min(viewport)  # fills the screen
    screenshot = tmp_path / "subject-view.png"
    assert browser.save_screenshot(str(screenshot))
    _check_png(screenshot)


def _pick(browser: webdriver.Chrome, picker: Select, session: str, other: str) -> None:
    """Pick ``session`` in the drop-down, as an operator would, and wait until the page has
    pinned it. Picking the option already shown fires no change (the page may be showing
    ``session`` by itself, as the newest running one), so ``other`` is picked first."""
    picker.select_by_value(other)
    picker.select_by_value(session)
    WebDriverWait(browser, TIMEOUT, poll_frequency=0.05).until(
        lambda driver: driver.current_url.endswith(f"?session={session}")
    )


def test_session_picker_switches_between_running_sessions(
    view: tuple[str, str], browser: webdriver.Chrome, service: str,
    sources: ProcessPoolExecutor,
) -> None:
    url, view_endpoint = view
    sessions = {"pick-a": (11, 40), "pick-b": (12, 25)}  # id: (seed, steps)
    browser.get(f"{url}/?token={TOKEN}")
    published = Published(service, tuple(sessions))
    try:
        futures = _start_sources(
            sources,
            [SourceSettings(sid, seed=seed, steps=steps, interval=0.03)
             for sid, (seed, steps) in sessions.items()],
            [service, view_endpoint],
        )
        picker = Select(browser.find_element(By.ID, "picker"))
        WebDriverWait(browser, TIMEOUT, poll_frequency=0.05).until(
            lambda driver: set(sessions) <= set(driver.execute_script(
                "return [...document.getElementById('picker').options].map(o => o.value)"
            ))
        )
        _pick(browser, picker, "pick-b", "pick-a")
        final_b = _wait(browser, _ended("pick-b", 25), "the end of pick-b")
        _pick(browser, picker, "pick-a", "pick-b")
        final_a = _wait(browser, _ended("pick-a", 40), "the end of pick-a")
        for future in futures:
            future.result()  # the source's own timeout guards it
        moves = published.collect().moves
    finally:
        published.close()
    assert final_b["agent"] == str(moves["pick-b"][25]["to_state"])
    assert final_a["agent"] == str(moves["pick-a"][40]["to_state"])
    assert browser.current_url.endswith("?session=pick-a")


def test_a_republished_recording_is_shown_as_it_was_recorded(
    view: tuple[str, str], browser: webdriver.Chrome, service: str,
    sources: ProcessPoolExecutor, tmp_path: Path,
) -> None:
    url, view_endpoint = view
    steps = 80
    recorded = tmp_path / "recorded"
    first = free_tcp_endpoint()
    # The recording is made on a service of its own network: on the view's network the
    # fixture's service would serve the session too.
    with service_process(first, recorded):  # closed: complete
        _wait_for_service(first)
        [future] = _start_sources(sources, [SourceSettings("rec", seed=SEED, steps=steps)],
                                  [first])
        original = future.result()  # the source's own timeout guards it
    recording = read_recording(recorded / "rec.mcap")
    last_move = recording.messages["/move"][-1][1]
    browser.get(f"{url}/?session=rec-replay&token={TOKEN}")
    with zenoh.open(peer_config((), [service, view_endpoint])) as session:
        result = publish_recording(session, recording, session_id="rec-replay", speed=0)
    assert result.moves_equal
    final = _wait(browser, _ended("rec-replay", steps), "the end of rec-replay")
    assert final["agent"] == str(last_move["to_state"])
    assert (final["correct"], final["wrong"]) == (
        str(original.correct_targets), str(original.wrong_targets)
    )


def test_a_view_started_during_a_session_infers_its_grid(
    browser: webdriver.Chrome, service: str, sources: ProcessPoolExecutor
) -> None:
    """The config went by before the view started: the grid is inferred from the states."""
    sid, steps = "late", 60
    published = Published(service, (sid,))
    try:
        [future] = _start_sources(
            sources, [SourceSettings(sid, seed=2, steps=steps, interval=0.2)], [service]
        )
        published.wait_for_move(sid, 5)
        with _view_running(connect=(service,)) as (url, _):
            browser.get(f"{url}/?session={sid}&token={TOKEN}")
            seen: list[dict[str, str]] = []
            final = _wait(browser, _ended(sid, steps), f"the end of {sid}", seen)
            title = browser.find_element(By.ID, "world-title").text
            cells = browser.find_elements(By.CSS_SELECTOR, "#world rect.cell")
        summary = future.result()  # the source's own timeout guards it
        published.collect()
    finally:
        published.close()
    followed = Followed(seen, final, summary, published.moves[sid], published.last_state[sid])
    # The view starts after move 5 and must still follow the session live: at 0.2 s per
    # step, 11 s remain, far more than a loaded machine needs to start it and a browser.
    assert len(_shown_steps(followed)) >= 3
    assert final["layout"] == "grid" and len(cells) == 25
    assert "inferred" in title, title
    assert final["agent"] == str(followed.moves[steps]["to_state"])


class _References(HTMLParser):
    """The ``src`` and ``href`` of a page's elements."""

    def __init__(self) -> None:
        super().__init__()
        self.found: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.found += [v for k, v in attrs if k in ("src", "href") and v]


def test_every_file_a_page_loads_is_served_by_the_view(view: tuple[str, str]) -> None:
    url, _ = view
    for page in ("/", "/subject"):
        with urllib.request.urlopen(f"{url}{page}?token={TOKEN}", timeout=TIMEOUT) as response:
            parser = _References()
            parser.feed(response.read().decode())
        files = [ref for ref in parser.found if ref.startswith("/static/")]
        others = [r for r in parser.found if r not in files and r not in ("/subject", "data:,")]
        assert files and others == [], f"{page} loads {others} from elsewhere"
        for ref in files:
            assert (STATIC / ref.removeprefix("/static/")).is_file()
            with urllib.request.urlopen(f"{url}{ref}?token={TOKEN}",
                                        timeout=TIMEOUT) as response:
                assert response.status == 200 and response.read()


def _body(browser: webdriver.Chrome) -> str:
    return browser.find_element(By.TAG_NAME, "body").text


def _until(browser: webdriver.Chrome, condition: Callable[[webdriver.Chrome], Any]) -> None:
    WebDriverWait(browser, TIMEOUT, poll_frequency=0.05).until(condition)


def test_the_pages_need_the_token_and_keep_it_across_a_reload(
    view: tuple[str, str], browser: webdriver.Chrome
) -> None:
    url, _ = view
    browser.get(f"{url}/")
    browser.delete_all_cookies()  # a browser that never had the token
    for page in ("/?session=tok", "/subject?session=tok"):
        browser.get(url + page)
        assert "403" in _body(browser) and "access token" in _body(browser), page
        assert browser.find_elements(By.ID, "view") == [], page
    browser.get(f"{url}/?session=tok&token={TOKEN}")

    def live(driver: webdriver.Chrome) -> bool:
        return (driver.find_element(By.ID, "link").get_attribute("textContent") == "live"
                and driver.find_element(By.ID, "view").get_attribute("data-session") == "tok")

    _until(browser, live)  # its WebSocket took the token, and follows the session
    assert browser.current_url == f"{url}/?session=tok"  # out of the address bar
    subject = browser.find_element(By.ID, "subject-link").get_attribute("href")
    assert subject == f"{url}/subject?session=tok&token={TOKEN}"
    browser.refresh()  # the cookie
    _until(browser, live)
    browser.get(f"{url}/subject?session=tok")
    _until(browser, lambda d: d.find_element(By.ID, "view").get_attribute("data-session") == "tok")


def test_another_site_cannot_use_the_view_nor_a_rebound_name(
    view: tuple[str, str], browser: webdriver.Chrome, other_site: int
) -> None:
    """A page of another site that has the token (leaked) still cannot open the view's
    WebSocket; the same page under an origin given to the view can (so the refusal is the
    view's, not the browser's). A name of another site that resolves to the view's address
    (DNS rebinding) gets 403, token or not."""
    url, _ = view
    socket = urllib.parse.quote(f"{url.replace('http://', 'ws://')}/ws?token={TOKEN}")
    for site, outcome in (("friend.test", "open"), ("attacker.test", "refused")):
        browser.get(f"http://{site}:{other_site}/?ws={socket}")
        _until(browser, lambda d: d.title in ("open", "refused"))
        assert browser.title == outcome, site
    port = url.rsplit(":", 1)[1]
    browser.get(f"http://rebound.test:{port}/?token={TOKEN}")
    assert "403" in _body(browser) and "--allow-host" in _body(browser)
    assert browser.find_elements(By.ID, "view") == []


def _message(kind: str, t_ns: int = 0, payload: Any = None, **fields: Any) -> protocol.Message:
    """A real message, through the wire encoding and back."""
    message = protocol.Message(kind, "s", 0, t_ns, fields, payload)
    return protocol.decode(protocol.encode(message), key_expr=protocol.key("s", kind))


def _move(step: int, cell: int, goal: bool = False) -> protocol.Message:
    return _message("move", step=step, from_state=cell, action="goal" if goal else "up",
                    to_state=cell, target_reached=goal)


def test_targets_are_judged_by_the_truth_of_their_step_in_any_order() -> None:
    view = SessionView("s")
    view.update(_move(5, 7, goal=True), 0)
    view.update(_message("truth", step=9, target=3, label=0), 0)
    assert list(view.targets) == [{"step": 5, "cell": 7, "status": "pending"}]
    view.update(_message("truth", step=5, target=7, label=0), 0)  # late truth
    view.update(_message("truth", step=12, target=3, label=0), 0)  # early truth
    view.update(_move(12, 4, goal=True), 0)
    assert [t["status"] for t in view.targets] == ["correct", "wrong"]


def test_latency_pairs_each_epoch_with_the_next_move() -> None:
    view = SessionView("s")
    epoch = {"step": 1, "signal": "features"}
    view.update(_move(1, 0), 1_000_000)
    patch = view.update(_message("epoch", payload=np.zeros(2, np.float32), **epoch), 2_000_000)
    assert patch is None  # move 2 not in yet
    patch = view.update(_move(2, 1), 5_500_000)
    assert patch is not None and patch["append"]["latency"] == [[1, 3.5]]  # ms


def test_a_new_config_under_a_used_id_starts_the_session_again() -> None:
    config = {"seed": 0, "world": "grid", "grid": 4, "frame": "feedback", "steps": 9,
              "learner": {"beta": 0.95},
              "dataset": {}, "signal": "features"}
    view = SessionView("s")
    assert view.update(_message("config", t_ns=10, **config), 0) is not None
    snapshot = view.snapshot()
    assert snapshot["layout"] == {"kind": "grid", "side": 4, "inferred": False}
    assert (snapshot["threshold"], snapshot["threshold_known"]) == (0.95, True)
    view.update(_move(1, 2), 0)
    assert view.update(_message("config", t_ns=10, **config), 0) is None  # re-sent: same
    assert view.starts_anew(_message("config", t_ns=11, **config))
    assert not view.starts_anew(_message("config", t_ns=10, **config))


def test_a_state_that_contradicts_itself_is_refused_and_changes_nothing() -> None:
    book = SessionBook()
    state = _message("state", payload=np.full(4, 0.5, np.float32), best_task=4, confident=False,
                     n_signals=0, class_counts=[0.0, 0.0], balanced_accuracy=None, points=[])
    with pytest.raises(ValueError, match="'best_task' must be an integer from 0 to 3; got 4"):
        book.update(state, 0)
    assert book.listing() == []


def test_layout_is_the_configs_grid_else_a_ranked_list() -> None:
    grid = {"kind": "grid", "side": 5, "inferred": False}
    assert layout_of({"grid": 5}) == grid
    assert layout_of({"grid": 5, "world": {"kind": "grid"}}) == grid
    assert layout_of({"grid": 5, "world": "line"}) == {"kind": "list"}
    assert layout_of({"grid": 10**6}) == {"kind": "list"}  # not a million-cell page
    # Config not seen: a grid only when the tasks make a square and all moves are grid moves.
    assert layout_of(None) == {"kind": "list"}
    assert layout_of(None, 25) == {"kind": "grid", "side": 5, "inferred": True}
    assert layout_of(None, 24) == {"kind": "list"}
    assert layout_of(None, 25, grid_actions=False) == {"kind": "list"}
    assert json.loads(json.dumps(SessionView("x").snapshot()))["threshold_known"] is False


def test_a_target_in_a_world_without_a_grid_is_judged_by_its_task_state() -> None:
    """Line world: task 1 (G2) is state 4; a target declared in state 4 is the user's when
    the truth names task 1, not when it names task 0."""
    config = {"seed": 0, "world": "line", "frame": "feedback", "steps": 9, "learner": {},
              "dataset": {}, "signal": "features"}
    view = SessionView("s")
    view.update(_message("config", t_ns=10, **config), 0)
    assert view.snapshot()["layout"] == {"kind": "list"}
    for step, target in ((1, 1), (2, 0)):
        view.update(_message("move", step=step, from_state=4, action="no-move", to_state=4,
                             target_reached=True), 0)
        view.update(_message("truth", step=step, target=target, label=0), 0)
    assert [(t["step"], t["cell"], t["status"]) for t in view.targets] == [
        (1, 4, "correct"), (2, 4, "wrong"),
    ]
