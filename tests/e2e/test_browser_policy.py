"""The service's Content-Security-Policy in a real headless Chromium: the dashboard and /docs work under it.

A policy that is too strict fails silently in a browser (a blocked script, a refused WebSocket);
each page here records every ``securitypolicyviolation`` from its first line on, and must
show its content with none, loading nothing from outside the cell PC.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from service.settings import load_settings
from tests.api.conftest import LiveServer, free_port, run_server
from tests.e2e.test_dashboard import Page, _chromium

pytestmark = pytest.mark.skipif(_chromium() is None, reason="Chromium is not installed (Debian package 'chromium')")

RECORD_VIOLATIONS = """
window.__violations = [];
document.addEventListener('securitypolicyviolation',
    e => window.__violations.push(e.violatedDirective + ' ' + e.blockedURI));
"""


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    settings = load_settings(
        None,
        state_dir=str(tmp_path_factory.mktemp("policy-state")),
        server__port=free_port(),
        server__token="policy-token",
    )
    yield from run_server(settings)


@pytest.fixture
def page(cell: LiveServer, tmp_path: pytest.TempPathFactory) -> Iterator[Page]:
    p = Page(str(_chromium()), tmp_path / "profile", tmp_path / "chromium.log")  # type: ignore[operator]
    try:
        p.call("Page.addScriptToEvaluateOnNewDocument", source=RECORD_VIOLATIONS)
        yield p
    finally:
        p.close()


def _outside(page: Page, cell: LiveServer) -> list[str]:
    urls = page.js("performance.getEntriesByType('resource').map(e => e.name)")
    return [u for u in urls if not u.startswith((cell.url + "/", cell.ws_url + "/", "blob:", "data:"))]


def test_dashboard_streams_and_shows_frames_under_the_policy(page: Page, cell: LiveServer) -> None:
    cell.wait_for(lambda h: h["status"] == "ok" and h["processing"]["ok"] >= 3, timeout_s=180.0, what="a running cell")
    page.goto(f"{cell.url}/")
    page.wait("document.getElementById('ws-state').textContent === 'live'", "the live stream", 30)
    page.wait("Number(document.getElementById('pose').dataset.seq) > 0", "a live pose", 15)
    page.wait("document.getElementById('frame-img').naturalWidth", "the frame image (a blob: URL)", 15)
    assert page.js("window.__violations") == []
    assert _outside(page, cell) == []


def test_docs_render_the_api_from_local_assets_under_the_policy(page: Page, cell: LiveServer) -> None:
    page.goto(f"{cell.url}/docs")
    n = page.wait("document.querySelectorAll('.opblock').length", "Swagger UI to list the operations", 20)
    assert n >= 10
    assert "/measure" in page.text("#swagger-ui")
    # "Try it out" on GET /health: Swagger UI calls the service and renders the highlighted answer
    page.click(".opblock-summary-path[data-path='/health']")
    page.wait("!!document.querySelector('.opblock.is-open .try-out__btn')", "the operation to open")
    page.click(".opblock.is-open .try-out__btn")
    page.wait("!!document.querySelector('.opblock.is-open .execute')", "the Execute button")
    page.click(".opblock.is-open .execute")
    page.wait(
        "[...document.querySelectorAll('.opblock.is-open .live-responses-table .response-col_status')]"
        ".some(e => e.textContent.trim() === '200')",
        "the live answer of /health",
        15,
    )
    assert "processing" in page.text(".opblock.is-open .live-responses-table .highlight-code")
    page.js("0")
    assert page.exceptions == []
    assert page.js("window.__violations") == []
    assert _outside(page, cell) == []
