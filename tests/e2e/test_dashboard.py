"""The dashboard in a real headless Chromium against the real service running the simulated cell.

The browser is driven over the Chrome DevTools protocol with the ``websockets`` package the
tests already use (no Selenium, no chromedriver): clicks and typing are real input events
(``Input.dispatchMouseEvent`` / ``Input.insertText``), reads are ``Runtime.evaluate`` in the page.
Faults are injected the way the API tests do it (unplug the simulated camera).
"""

from __future__ import annotations

import base64
import contextlib
import itertools
import json
import math
import re
import shutil
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from websockets.sync.client import connect

from service.settings import load_settings
from tests.api.conftest import LiveServer, free_port, run_server

TOKEN = "dashboard-test-token"
CHROMIUM_FLAGS = [
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-dev-shm-usage",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-extensions",
    "--mute-audio",
    "--window-size=1280,1000",
    "--remote-debugging-address=127.0.0.1",
    "--remote-debugging-port=0",
]


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


pytestmark = pytest.mark.skipif(
    _chromium() is None, reason="Chromium is not installed (Debian package 'chromium'; deploy/dev.sh setup installs it)"
)


class Page:
    """One Chromium tab over the DevTools protocol: just what these tests need."""

    def __init__(self, binary: str, profile: Path, log: Path) -> None:
        self._log = log.open("wb")
        self.proc = subprocess.Popen(
            [binary, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "about:blank"],
            stdin=subprocess.DEVNULL,
            stdout=self._log,
            stderr=self._log,
        )
        self.exceptions: list[dict[str, Any]] = []
        self._id = 0
        self._stack = contextlib.ExitStack()
        try:
            port = self._devtools_port(profile / "DevToolsActivePort", timeout_s=30)
            targets = httpx.get(f"http://127.0.0.1:{port}/json/list", timeout=5).json()
            url = next(t["webSocketDebuggerUrl"] for t in targets if t["type"] == "page")
            self.ws = self._stack.enter_context(connect(url, max_size=None, open_timeout=10))
            self.call("Runtime.enable")
            self.call("Page.enable")
        except BaseException:
            self.close()
            raise

    def _devtools_port(self, path: Path, timeout_s: float) -> int:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"chromium exited with {self.proc.returncode}; see {self._log.name}")
            with contextlib.suppress(FileNotFoundError, ValueError, IndexError):
                return int(path.read_text().splitlines()[0])
            time.sleep(0.05)
        raise RuntimeError(f"chromium opened no DevTools port within {timeout_s} s; see {self._log.name}")

    def call(self, method: str, timeout_s: float = 15.0, **params: Any) -> dict[str, Any]:
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"no DevTools answer to {method} within {timeout_s} s")
            msg = json.loads(self.ws.recv(timeout=remaining))
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return dict(msg.get("result", {}))
            if msg.get("method") == "Runtime.exceptionThrown":
                self.exceptions.append(msg["params"]["exceptionDetails"])

    def js(self, expression: str) -> Any:
        r = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in r:
            raise RuntimeError(f"{expression!r} raised {r['exceptionDetails']}")
        return r["result"].get("value")

    def wait(self, expression: str, what: str, timeout_s: float = 10.0) -> Any:
        deadline = time.monotonic() + timeout_s
        value = None
        while time.monotonic() < deadline:
            value = self.js(expression)
            if value:
                return value
            time.sleep(0.1)
        raise AssertionError(f"timed out after {timeout_s} s waiting for {what}; last value: {value!r}")

    def goto(self, url: str) -> None:
        self.call("Page.navigate", url=url)
        self.wait("document.readyState === 'complete'", f"{url} to load")

    def text(self, selector: str) -> str:
        return str(self.js(f"document.querySelector({json.dumps(selector)}).textContent"))

    def click(self, selector: str) -> None:
        """A real mouse click at the element's centre (not el.click()): it must be visible and on top."""
        box = self.wait(
            f"""(() => {{
            const e = document.querySelector({json.dumps(selector)});
            e.scrollIntoView({{block: 'center'}});
            const r = e.getBoundingClientRect();
            const x = r.x + r.width / 2, y = r.y + r.height / 2;
            return e.contains(document.elementFromPoint(x, y)) && [x, y];
        }})()""",
            f"{selector} to be visible and on top",
            5,
        )
        for kind in ("mousePressed", "mouseReleased"):
            self.call("Input.dispatchMouseEvent", type=kind, x=box[0], y=box[1], button="left", clickCount=1)

    def type(self, selector: str, text: str) -> None:
        """Replace the field's content as a user would: focus, select all, type (or delete)."""
        self.js(f"(() => {{ const e = document.querySelector({json.dumps(selector)}); e.focus(); e.select(); }})()")
        if text:
            self.call("Input.insertText", text=text)
        else:
            for kind in ("rawKeyDown", "keyUp"):
                self.call(
                    "Input.dispatchKeyEvent", type=kind, key="Backspace", code="Backspace", windowsVirtualKeyCode=8
                )

    def screenshot(self, path: Path) -> None:
        path.write_bytes(base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"]))

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._stack.close()
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        self._log.close()


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    state = tmp_path_factory.mktemp("dash-state")
    settings = load_settings(None, state_dir=str(state), server__port=free_port(), server__token=TOKEN)
    servers = run_server(settings)
    server = next(servers)
    try:
        # the first start on a fresh machine compiles the numba kernels (a minute on a slow CI machine):
        # wait for it here so the page's own waits measure the page, not the warm-up
        server.wait_for(
            lambda h: h["status"] == "ok" and h["processing"]["ok"] >= 3, timeout_s=180.0, what="a running cell"
        )
        yield server
    finally:
        servers.close()  # run_server's finally stops uvicorn and the worker


@pytest.fixture(scope="module")
def page(cell: LiveServer, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Page]:
    tmp = tmp_path_factory.mktemp("chromium")
    p = Page(str(_chromium()), tmp / "profile", tmp / "chromium.log")
    try:
        p.goto(f"{cell.url}/")
        # the first /health fills the device cards and moves everything below them: let it land
        p.wait("document.getElementById('status').dataset.state !== 'unknown'", "the first health report")
        yield p
    finally:
        p.close()


def _live_pose(page: Page) -> dict[str, Any]:
    """What the live-pose card shows, read in one evaluation so the values belong together."""
    return page.js("""(() => ({
        seq: Number(document.getElementById('pose').dataset.seq),
        xyz: ['x', 'y', 'z'].map(a => Number(document.getElementById('pose-' + a).textContent)),
        dev: Number(document.getElementById('dev-pos').textContent),
        mode: document.getElementById('pose-mode').textContent,
        targets: document.getElementById('pose-targets').textContent,
    }))()""")


def _position(T: list[list[float]]) -> list[float]:
    return [T[0][3], T[1][3], T[2][3]]


class StreamRecorder:
    """Every result of the pose stream (no decimation), keyed by seq, read by a thread."""

    def __init__(self, ws_url: str) -> None:
        self.results: dict[int, dict[str, Any]] = {}
        self._stop = threading.Event()
        self._stack = contextlib.ExitStack()
        self._ws = self._stack.enter_context(connect(f"{ws_url}/ws/poses", max_size=None, open_timeout=10))
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                r = json.loads(self._ws.recv(timeout=0.5))
            except TimeoutError:
                continue
            except Exception:
                return
            if r.get("ok"):
                self.results[int(r["seq"])] = r

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._stack.close()

    def path_length_mm(self, seq_a: int, seq_b: int) -> float:
        """How far the camera moved along the stream between two results (triangle inequality bound)."""
        lo, hi = sorted((seq_a, seq_b))
        seqs = [s for s in sorted(self.results) if lo <= s <= hi]
        assert seqs and seqs[0] == lo and seqs[-1] == hi, f"the stream recorder missed seq {lo} or {hi}"
        pts = [_position(self.results[s]["T_field_camera"]) for s in seqs]
        return sum(math.dist(a, b) for a, b in itertools.pairwise(pts))


def test_status_bar_and_device_cards_show_ok_once_the_cell_runs(page: Page) -> None:
    page.wait("document.getElementById('status').textContent === 'ok'", "the overall status 'ok'", 30)
    cam = '[data-camera="cam0"]'
    page.wait(f"document.querySelector('{cam}')?.dataset.state === 'ok'", "camera cam0 ok")
    assert page.text(f"{cam} .state") == "ok" and page.text(f"{cam} .device-error") == ""
    assert re.search(r"exposure \d+ µs \(auto\)", page.text(f"{cam} .device-facts"))
    assert page.text("#robot-card .state") == "ok"
    rows = page.js("""[...document.querySelectorAll('#calibration tbody tr')].map(
        r => [r.dataset.kind, r.className, r.cells[1].textContent, r.cells[2].textContent])""")
    assert sorted(r[0] for r in rows) == ["camera", "field", "handeye", "robot"]
    needed = [r for r in rows if r[0] != "robot"]
    assert all(cls == "" and version.startswith("v") and source for _, cls, version, source in needed), rows
    # no robot model stored: optional, the nominal model stands (not shown as missing)
    assert [r[1:] for r in rows if r[0] == "robot"] == [
        ["optional", "–", page.text('[data-kind="robot"] td:last-child')]
    ]
    assert "nominal model" in page.text('[data-kind="robot"] td:last-child')
    page.wait("document.getElementById('ws-state').textContent === 'live'", "the live stream")
    page.wait("/^\\d+\\.\\d fps$/.test(document.getElementById('fps').textContent)", "a frame rate")
    page.wait("/ms/.test(document.getElementById('latency').textContent)", "a latency")
    assert page.text("#ws-drops").isdigit()


def test_live_pose_updates_and_agrees_with_the_stream_and_the_latest_pose(page: Page, cell: LiveServer) -> None:
    stream = StreamRecorder(cell.ws_url)
    try:
        page.wait("Number(document.getElementById('pose').dataset.seq) > 0", "a first live pose")
        first = _live_pose(page)
        page.wait(f"Number(document.getElementById('pose').dataset.seq) > {first['seq']}", "the next live pose", 5)
        shown = _live_pose(page)
        with cell.client() as c:
            latest = c.get("/poses/latest").json()
        time.sleep(0.3)  # let the recorder see the latest result too
    finally:
        stream.close()
    assert shown["xyz"] != first["xyz"], "the live pose did not change while the simulated robot moves"
    # what the page shows is exactly the stream's result of that seq (to the 0.01 mm it prints) ...
    streamed = stream.results[shown["seq"]]
    for shown_mm, streamed_mm in zip(shown["xyz"], _position(streamed["T_field_camera"]), strict=True):
        assert abs(shown_mm - streamed_mm) <= 0.0051
    assert abs(shown["dev"] - streamed["deviation"]["position_mm"]) <= 0.00051
    assert shown["targets"] == f"{streamed['n_coded']} / {streamed['n_uncoded']}"
    assert shown["mode"].split()[0] == streamed["mode"]
    # ... and differs from GET /poses/latest by no more than the camera travelled in between
    moved_mm = stream.path_length_mm(shown["seq"], latest["seq"])
    gap_mm = math.dist(shown["xyz"], _position(latest["T_field_camera"]))
    assert gap_mm <= moved_mm + 0.01, (gap_mm, moved_mm, shown["seq"], latest["seq"])


def test_latest_frame_image_loads_and_refreshes_about_every_second(page: Page) -> None:
    width = page.wait("document.getElementById('frame-img').naturalWidth", "the frame image to load")
    assert 0 < width <= 800
    first = page.js("document.getElementById('frame-img').src")
    t0 = time.monotonic()
    page.wait(f"document.getElementById('frame-img').src !== {json.dumps(first)}", "a refreshed frame", 5)
    assert time.monotonic() - t0 < 3.0
    assert page.js("document.getElementById('frame-failure').hidden") is True


def test_measure_now_without_token_is_unauthorized_and_with_token_gives_a_deviation(
    page: Page, cell: LiveServer
) -> None:
    page.type("#token", "")
    page.click("#measure-btn")
    page.wait("document.getElementById('measure-result').dataset.state === 'failed'", "the refused measurement")
    assert page.js("document.getElementById('measure-result').dataset.reason") == "unauthorized"
    refused = page.text("#measure-result")
    assert "unauthorized" in refused and "Bearer" in refused  # the reason and the server's sentence

    page.type("#token", TOKEN)
    assert page.js("localStorage.getItem('posecell.token')") == TOKEN
    page.click("#measure-btn")
    page.wait("document.getElementById('measure-result').dataset.state === 'ok'", "the measurement result")
    facts = page.js("""Object.fromEntries([...document.querySelectorAll('#measure-result dt')].map(
        dt => [dt.textContent, dt.nextElementSibling.textContent]))""")
    dev_mm = float(facts["Deviation"].split(" mm")[0])
    seq = int(facts["Camera · seq · mode"].split(" · ")[1])
    # the number on screen is the stored triggered measurement of that frame
    with cell.client() as c:
        rows = c.get("/measurements", params={"limit": 50}).json()["measurements"]
    stored = next(r for r in rows if r["result"].get("seq") == seq)
    # the column holds the full value; the screen shows 3 decimals of the message's 4: within 0.00055 mm
    assert stored["ok"] is True and abs(dev_mm - stored["deviation_position_mm"]) <= 0.00056
    assert 0 < dev_mm < 20  # nominal vs true robot pose in the simulated cell: a few mm, never zero


def test_unplugged_camera_card_says_disconnected_and_why_then_recovers(page: Page, cell: LiveServer) -> None:
    cam = '[data-camera="cam0"]'
    page.wait(f"document.querySelector('{cam}')?.dataset.state === 'ok'", "camera cam0 ok")
    driver = cell.worker.cameras["cam0"].driver
    driver.unplug()
    try:
        page.wait(f"document.querySelector('{cam}').dataset.state === 'disconnected'", "camera disconnected", 15)
        assert page.text(f"{cam} .state") == "disconnected"
        with cell.client() as c:
            sentence = c.get("/health").json()["cameras"]["cam0"]["error"]
        assert "unplugged" in sentence
        page.wait(
            f"document.querySelector('{cam} .device-error').textContent === {json.dumps(sentence)}",
            "the camera's error sentence",
        )
        assert page.text("#status") == "degraded"
        page.wait("document.getElementById('pose').classList.contains('stale')", "the live pose marked stale", 6)
        assert "no new result" in page.text("#pose-age")
        page.wait(
            "/camera_disconnected/.test(document.getElementById('frame-failure').textContent)",
            "the frame marked as the last one before the camera went away",
            5,
        )
    finally:
        driver.plug()
    page.wait(f"document.querySelector('{cam}').dataset.state === 'ok'", "camera cam0 back to ok", 20)
    page.wait("document.getElementById('status').textContent === 'ok'", "the overall status back to ok")
    assert page.text(f"{cam} .device-error") == ""
    page.wait("!document.getElementById('pose').classList.contains('stale')", "fresh live poses again")
    page.wait("document.getElementById('frame-failure').hidden", "a live frame again", 5)


def test_an_overexposed_camera_card_counts_its_saturated_targets(page: Page, cell: LiveServer) -> None:
    cam = '[data-camera="cam0"]'
    page.wait(f"document.querySelector('{cam}')?.dataset.state === 'ok'", "camera cam0 ok")
    # the simulated optics are sharp: the card gives their blur (0.66 px) and says nothing of the focus
    page.wait(f"/blur 0\\.\\d+ px/.test(document.querySelector('{cam} .device-facts').textContent)", "the blur", 15)
    assert "out of focus" not in page.text(f"{cam} .device-facts")
    worker = cell.worker
    before = worker.settings.cameras[0]
    over = before.model_copy(
        update={"exposure_us": 8000.0, "auto_exposure": before.auto_exposure.model_copy(update={"enabled": False})}
    )
    assert worker.reconfigure_camera(over) == ""
    try:
        page.wait(
            f"/[1-9]\\d* targets saturated/.test(document.querySelector('{cam} .device-facts').textContent)",
            "the saturated targets counted on the card",
            15,
        )
        assert "shorten the exposure" in page.js(f"document.querySelector('{cam} .device-facts').title")
        assert page.text(f"{cam} .state") == "ok"  # measured all the same
    finally:
        assert worker.reconfigure_camera(before) == ""
    page.wait(
        f"!/saturated/.test(document.querySelector('{cam} .device-facts').textContent)", "no saturated targets", 20
    )


def test_a_camera_card_counts_the_defect_pixels_its_frames_are_patched_for(
    page: Page, cell: LiveServer, tmp_path
) -> None:
    from service.core.targets.defects import DefectMap
    from service.store import formats

    cam = '[data-camera="cam0"]'
    page.wait(f"document.querySelector('{cam}')?.dataset.state === 'ok'", "camera cam0 ok")
    uv, dead = [[10, 20], [500, 400], [900, 77]], [False, True, False]  # two hot, one dead
    formats.write_defects(tmp_path / "defects.json", DefectMap(1300, 1030, uv, dead))
    worker = cell.worker
    before = worker.settings.cameras[0]
    assert worker.reconfigure_camera(before.model_copy(update={"defects": tmp_path / "defects.json"})) == ""
    try:
        page.wait(
            f"/3 defect pixels patched \\(1 dead\\)/.test(document.querySelector('{cam} .device-facts').textContent)",
            "the defect map on the card",
            15,
        )
    finally:
        assert worker.reconfigure_camera(before) == ""
    page.wait(f"!/defect pixels/.test(document.querySelector('{cam} .device-facts').textContent)", "no map", 20)


def test_a_camera_cards_button_maps_the_hot_pixels_from_dark_frames_and_puts_the_map_in_use(
    page: Page, cell: LiveServer
) -> None:
    cam = '[data-camera="cam0"]'
    note = f"document.querySelector('{cam} .device-note')"
    page.wait(f"document.querySelector('{cam}')?.dataset.state === 'ok'", "camera cam0 ok")
    page.type("#token", "")
    page.click(f"{cam} .defects-map")
    page.wait(f"{note}.dataset.state === 'failed'", "the refused request")
    assert "unauthorized" in page.text(f"{cam} .device-note") and "API token" in page.text(f"{cam} .device-note")
    assert cell.worker.settings.cameras[0].defects is None  # refused: nothing changed

    before = cell.worker.settings.cameras[0]
    page.type("#token", TOKEN)
    try:
        page.click(f"{cam} .defects-map")
        said = page.wait(f"{note}.dataset.state === 'ok' && {note}.textContent", "the map taken from dark frames", 30)
        mapped = re.fullmatch(r"(\d+) defect pixels mapped from 8 dark frames, patched from now on", said)
        assert mapped, said
        path = cell.worker.settings.cameras[0].defects
        assert path is not None and path.name == "defects-cam0.json" and path.exists()
        # the card's facts say the map the frames are patched with
        page.wait(
            f"/{mapped[1]} defect pixels patched/.test(document.querySelector('{cam} .device-facts').textContent)",
            "the map in use on the card",
            15,
        )
        assert not page.js(f"document.querySelector('{cam} .defects-map').disabled")
    finally:
        assert cell.worker.reconfigure_camera(before) == ""
    page.wait(f"!/defect pixels/.test(document.querySelector('{cam} .device-facts').textContent)", "no map", 20)


def test_page_loads_nothing_from_outside_and_raises_no_script_error(page: Page, cell: LiveServer) -> None:
    urls = page.js("performance.getEntriesByType('resource').map(e => e.name)")
    assert urls, "the page fetched nothing"
    outside = [u for u in urls if not u.startswith((cell.url + "/", "blob:", "data:"))]
    assert outside == []
    page.js("0")  # drain pending DevTools events
    assert page.exceptions == []


def test_a_camera_cards_dead_pixel_button_says_why_frames_without_the_card_are_refused(
    page: Page, cell: LiveServer
) -> None:
    """The simulated cell has no white card before its lens: its frames are not lit flat fields, and the
    card says the service's refusal; nothing changes."""
    cam = '[data-camera="cam0"]'
    note = f"document.querySelector('{cam} .device-note')"
    page.wait(f"document.querySelector('{cam}')?.dataset.state === 'ok'", "camera cam0 ok")
    page.type("#token", TOKEN)
    page.click(f"{cam} .defects-dead")
    said = page.wait(f"{note}.dataset.state === 'failed' && {note}.textContent", "the refused frames", 30)
    assert said.startswith("bad_image: camera cam0: flat frame 1 is not lit") and "white card" in said, said
    assert cell.worker.settings.cameras[0].defects is None
    assert not page.js(f"document.querySelector('{cam} .defects-dead').disabled")
