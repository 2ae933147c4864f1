"""``/docs``: Swagger UI served by the service itself (the cell PC has no internet).

FastAPI's own ``/docs`` page loads Swagger UI and its favicon from CDNs; here the
assets come from the ``swagger-ui-bundle-v2`` package (swagger-ui's ``dist``
files, 5.x: FastAPI's schema is OpenAPI 3.1, which Swagger UI 4 cannot show)
and are mounted under ``/docs/assets``. ReDoc is switched off: no package ships
it, and one documentation page is enough.

The page's one inline script (Swagger UI's start-up call) is allowed in its
Content-Security-Policy by its hash, so no other inline script can run; the
rest of the policy is the dashboard's (Swagger UI needs no inline style, and
its icons are data: images). ``tests/e2e/test_browser_policy.py`` renders the
page and runs "Try it out" in Chromium with no policy violation.
"""

from __future__ import annotations

import base64
import hashlib
import re

from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles
from swagger_ui_bundle import swagger_ui_path

ASSETS = "/docs/assets"
_INLINE_SCRIPT = re.compile(r"<script>(.*?)</script>", re.DOTALL)
_CSP = (
    "default-src 'self'; script-src 'self' {hashes}; style-src 'self'; "
    "img-src 'self' data:; connect-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self'; "
    "frame-ancestors 'none'"
)


def install(app: FastAPI) -> None:
    """Add ``GET /docs`` and its assets; the app must be made with ``docs_url=None, redoc_url=None``."""
    app.mount(ASSETS, StaticFiles(directory=str(swagger_ui_path)), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    def swagger_ui(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        page = get_swagger_ui_html(
            openapi_url=f"{root}{app.openapi_url}",
            title=f"{app.title} - API",
            swagger_js_url=f"{root}{ASSETS}/swagger-ui-bundle.js",
            swagger_css_url=f"{root}{ASSETS}/swagger-ui.css",
            swagger_favicon_url=f"{root}{ASSETS}/favicon-32x32.png",
            swagger_ui_parameters={"validatorUrl": None},  # no badge fetched from validator.swagger.io
        )
        hashes = " ".join(
            "'sha256-" + base64.b64encode(hashlib.sha256(script.encode()).digest()).decode() + "'"
            for script in _INLINE_SCRIPT.findall(bytes(page.body).decode())
        )
        page.headers["Content-Security-Policy"] = _CSP.format(hashes=hashes)
        return page
