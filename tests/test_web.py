"""What people and programs see of a real ``maxfs serve``: the job page, the API docs, the OpenAPI.

One server (auth on, one embedded worker) for the module, and one headless Chromium (Debian's, driven
by Selenium; see :mod:`tests.browser`). Alice signs in on the page, watches a running job's progress
change and its previews load, cancels it, starts another one and sees it finish; Bob's job never shows
on her page, an admin sees both. ``/docs`` and ``/redoc`` load with every request answered 200 by the
server itself (other hosts resolve nowhere, so a CDN would show as a failed request). The live
``/openapi.json`` is the one the code generates, and says what the routes really answer.
``MAXFS_SCREENSHOTS=docs`` saves the screenshots there (else to a temporary folder).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

from maxfs.service.cli.client import MaxfsClient
from maxfs.storage.errors import MaxfsError
from maxfs.worker import synthetic
from tests import browser
from tests.procs import Server, poll_until

#: The running job: the MILP solver on 128 x 128 pixels in 16 x 16 tiles takes tens of seconds on one
#: worker, long enough to watch; the job started from the page is small and exact (a second or two).
SLOW = {"solver": "milp", "eps": 1.0, "tile": 16, "milp_time_limit": 5.0}
QUICK = {"solver": "exact", "eps": 1.0, "tile": 16}


@pytest.fixture(scope="module")
def shots(tmp_path_factory: pytest.TempPathFactory) -> Path:
    where = os.environ.get("MAXFS_SCREENSHOTS")
    return Path(where) if where else tmp_path_factory.mktemp("screenshots")


@pytest.fixture(scope="module")
def server(module_server_factory, tmp_path_factory: pytest.TempPathFactory) -> Server:
    tmp = tmp_path_factory.mktemp("page")
    s = module_server_factory(tmp / "data", logs=tmp, workers=1, auth=True)
    s.tokens = {"alice": s.token("alice"), "bob": s.token("bob"), "root": s.token("root", admin=True)}
    return s


@pytest.fixture(scope="module")
def chrome(server: Server):
    browser.require_browser()
    driver = browser.start_chromium()
    yield driver
    browser.stop_chromium(driver)


def _job(client: MaxfsClient, size: int, params: dict, start: bool, scene=synthetic.sphere) -> str:
    s = scene(8, size, specular=0.0)
    job = client.create_job(k=8, height=size, width=size, dtype="uint8", lights=s.lights.tolist(), **params)
    for i in range(8):
        client.upload_image(job["id"], i, s.images[i].astype(np.uint8))
    client.upload_mask(job["id"], s.mask)
    if start:
        client.start(job["id"])
    return job["id"]


def _js(driver, script: str, *args):
    return driver.execute_script(script, *args)


def _text(driver, css: str) -> str:
    return _js(driver, "const e = document.querySelector(arguments[0]); return e && e.textContent;", css)


def _rows(driver) -> list[str]:
    return _js(driver, "return [...document.querySelectorAll('#job-table tbody tr')].map(r => r.dataset.job)")


def _previews(driver) -> dict[str, int]:
    """Preview name -> natural width of the loaded image (0 = not loaded)."""
    return _js(
        driver,
        "const out = {};"
        "for (const f of document.querySelectorAll('#d-previews figure:not([hidden])')) {"
        "  const i = f.querySelector('img'); out[f.dataset.preview] = i.complete ? i.naturalWidth : 0; }"
        "return out;",
    )


def _sign_in(driver, server: Server, user: str) -> None:
    driver.get(server.url + "/")
    poll_until(lambda: _js(driver, "return !document.querySelector('#sign-in').hidden"), 20, "sign-in form")
    _js(driver, "document.querySelector('#token').value = arguments[0];", server.tokens[user])
    driver.find_element("css selector", "#sign-in-button").click()
    try:
        poll_until(lambda: _js(driver, "return !document.querySelector('#jobs').hidden"), 30, user)
    except AssertionError as e:
        said = _text(driver, "#sign-in-error"), _text(driver, "#list-error"), driver.get_log("browser")
        raise AssertionError(f"{e}; the page said {said}") from None


def _select(driver, job_id: str) -> None:
    poll_until(lambda: job_id in _rows(driver), 20, f"job {job_id} listed")
    driver.find_element("css selector", f'tr[data-job="{job_id}"]').click()
    poll_until(lambda: _text(driver, "#d-id") == job_id, 10, "job details shown")


def _documents_purge(url: str) -> bool:
    import httpx

    op = httpx.get(url + "/openapi.json", timeout=30).json()["paths"]["/jobs/{job_id}"]["delete"]
    return any(p["name"] == "purge" for p in op.get("parameters", []))


def _accept_confirm(driver) -> None:
    from selenium.common.exceptions import NoAlertPresentException

    def accepted() -> bool:
        try:
            driver.switch_to.alert.accept()
            return True
        except NoAlertPresentException:
            return False

    poll_until(accepted, 10, "the confirmation dialog")


@pytest.mark.smoke
def test_job_page(server: Server, chrome, shots: Path) -> None:
    url = server.url
    with (
        MaxfsClient(url, server.tokens["alice"]) as alice,
        MaxfsClient(url, server.tokens["bob"]) as bob,
    ):
        bobs = _job(bob, 16, QUICK, start=False)
        slow = _job(alice, 128, SLOW, start=True, scene=synthetic.bump_scene)  # fills the view
        quick = _job(alice, 48, QUICK, start=False)

        # a wrong token is refused with the server's reason; nothing is stored
        chrome.get(url + "/")
        poll_until(lambda: _js(chrome, "return !document.querySelector('#sign-in').hidden"), 20, "sign-in")
        _js(chrome, "document.querySelector('#token').value = 'mfs_wrong';")
        chrome.find_element("css selector", "#sign-in-button").click()
        poll_until(lambda: "not valid" in (_text(chrome, "#sign-in-error") or ""), 10, "refusal shown")
        assert _js(chrome, "return sessionStorage.getItem('maxfs-token')") is None
        browser.screenshot(chrome, shots / "job-page-sign-in.png")

        # alice signs in: her two jobs, never bob's
        _sign_in(chrome, server, "alice")
        poll_until(lambda: {slow, quick} <= set(_rows(chrome)), 20, "alice's jobs listed")
        assert bobs not in _rows(chrome) and bobs not in chrome.page_source
        assert _js(chrome, "return sessionStorage.getItem('maxfs-token')") == server.tokens["alice"]
        assert _js(chrome, "return localStorage.length") == 0

        # the running job: progress changes while it runs, previews load (partial)
        _select(chrome, slow)
        poll_until(lambda: _text(chrome, "#d-state") == "running", 60, "slow job running")
        first = _text(chrome, '#d-stats dd[data-stat="tiles"]')
        poll_until(
            lambda: (
                _text(chrome, '#d-stats dd[data-stat="tiles"]') != first
                and _text(chrome, "#d-state") == "running"
            ),
            60,
            f"tiles to move on from {first} while running",
        )
        assert _text(chrome, '#d-stats dd[data-stat="pixels-s"]') != "–"  # a pixel rate
        assert _text(chrome, '#d-stats dd[data-stat="eta"]') != "–"  # and an ETA
        row = _js(chrome, f"return document.querySelector('tr[data-job=\"{slow}\"]').innerText")
        assert "running" in row and "/ 64" in row  # 64 tiles in the list too
        poll_until(
            lambda: all(_previews(chrome).get(n) == 128 for n in ("normal", "albedo", "inlier_count")),
            30,
            "previews of the running job loaded",
        )
        assert "partial" in _text(chrome, "#d-partial")
        if os.environ.get("MAXFS_SCREENSHOTS"):  # for the README: a third of the tiles, previews caught up
            poll_until(lambda: alice.status(slow)["progress"]["tiles_done"] >= 22, 120, "a third done")
            time.sleep(3)
        browser.screenshot(chrome, shots / "job-page-running.png")

        # cancel from the page
        chrome.find_element("css selector", "#d-cancel").click()
        poll_until(lambda: _text(chrome, "#d-state") == "cancelled", 60, "cancelled on the page")
        assert alice.status(slow)["state"] == "cancelled"
        assert _js(chrome, "return document.querySelector('#d-start').textContent") == "Resume"

        # start the other job from the page and see it finish, with every preview
        _select(chrome, quick)
        assert "not been started" in _text(chrome, "#d-no-results")
        chrome.find_element("css selector", "#d-start").click()
        poll_until(lambda: _text(chrome, "#d-state") == "done", 90, "quick job done on the page")
        want = {"normal": 48, "albedo": 48, "inlier_count": 48}
        st = alice.status(quick)
        if server.data.joinpath("jobs", quick, "results.zarr", "depth").exists():
            want["depth"] = 48  # depth is integrated after the job is done, where the server does it
        poll_until(lambda: _previews(chrome) == want, 30, f"previews {want} of the done job")
        certified = f"{100 * st['progress']['certified_share']:.1f} %"
        assert _text(chrome, '#d-stats dd[data-stat="certified"]') == certified
        links = _js(
            chrome, "return [...document.querySelectorAll('#d-downloads a')].map(a => a.dataset.download)"
        )
        assert "results.zip" in links and "normal.npy" in links
        browser.screenshot(chrome, shots / "job-page-done.png")

        # delete the cancelled job for good, where the server can (DELETE /jobs/{id}?purge=true): the
        # page offers the button only when the server's OpenAPI documents it
        everyone = {slow, quick, bobs}
        _select(chrome, slow)
        can_delete = _js(chrome, "return !document.querySelector('#d-delete').hidden")
        assert can_delete == _documents_purge(url)
        if can_delete:
            chrome.find_element("css selector", "#d-delete").click()
            _accept_confirm(chrome)
            poll_until(lambda: slow not in _rows(chrome), 30, "deleted job gone from the list")
            assert _js(chrome, "return document.querySelector('#detail').hidden")
            with pytest.raises(MaxfsError):
                alice.status(slow)
            everyone.remove(slow)

        # the token never went into a URL; every request stayed on this server
        for req in browser.network(chrome):
            assert server.tokens["alice"] not in req.url
            assert req.url.startswith((url + "/", "data:", "blob:")), req.url

        # an admin sees everyone's jobs
        chrome.find_element("css selector", "#sign-out").click()
        _sign_in(chrome, server, "root")
        poll_until(lambda: everyone <= set(_rows(chrome)), 20, "every job for the admin")


def test_docs_load_with_no_request_leaving_the_server(server: Server, chrome, shots: Path) -> None:
    url = server.url
    browser.network(chrome)  # forget earlier requests
    chrome.get(url + "/docs")
    poll_until(
        lambda: _js(chrome, "return document.querySelectorAll('.opblock').length") >= 10, 30, "Swagger UI"
    )
    assert _js(chrome, "return !!document.querySelector('button.authorize')"), "no Authorize button"
    browser.screenshot(chrome, shots / "api-docs.png")
    # authorize with a token and run GET /jobs from the docs page
    chrome.find_element("css selector", "button.authorize").click()
    poll_until(lambda: _js(chrome, "return !!document.querySelector('.modal-ux input')"), 10, "auth dialog")
    chrome.find_element("css selector", ".modal-ux input").send_keys(server.tokens["alice"])
    chrome.find_element("css selector", ".modal-ux button.authorize").click()
    chrome.find_element("css selector", ".modal-ux button.btn-done").click()
    chrome.find_element("css selector", "#operations-jobs-list_jobs_get .opblock-summary").click()
    poll_until(lambda: _js(chrome, "return !!document.querySelector('.try-out__btn')"), 10, "Try it out")
    chrome.find_element("css selector", ".try-out__btn").click()
    chrome.find_element("css selector", ".execute").click()
    poll_until(
        lambda: (
            _js(
                chrome,
                "const c = document.querySelector('.live-responses-table tr.response .response-col_status');"
                "return c ? c.textContent.trim() : null;",
            )
            == "200"
        ),
        20,
        "GET /jobs answered 200 in Swagger UI",
    )

    chrome.get(url + "/redoc")
    poll_until(
        lambda: _js(chrome, "return (document.querySelector('h1') || {}).textContent || ''").startswith(
            "maxfs-ps"
        ),
        30,
        "ReDoc",
    )
    poll_until(lambda: "Upload an image" in chrome.page_source, 20, "ReDoc lists the operations")

    requests = browser.network(chrome)
    assert any(r.url.endswith("/static/docs/swagger-ui-bundle.js") for r in requests)
    assert any(r.url.endswith("/static/docs/redoc.standalone.js") for r in requests)
    for r in requests:
        if r.url.startswith(("data:", "blob:")):
            continue
        if r.blocked == "csp":  # refused by the page's Content-Security-Policy: never sent
            assert r.status is None, r
            continue
        assert r.url.startswith(url + "/"), f"a request left the server: {r.url} ({r.failed or r.status})"
        if r.url.startswith(url + "/jobs"):
            continue  # the API call made from Swagger UI, checked above
        assert r.status == 200 and r.failed is None, f"{r.url}: {r.status} {r.failed}"


# -- the OpenAPI document, checked against the live server ------------------------------------------

NPY = "application/octet-stream"  # NPY has no registered media type
#: Every operation: the statuses it documents (besides its success) and its success status and media type.
OPERATIONS = {
    ("post", "/jobs"): ({401, 413, 422, 429, 507}, "201", "application/json"),
    ("get", "/jobs"): ({401, 422}, "200", "application/json"),
    ("get", "/jobs/{job_id}"): ({401, 404, 422}, "200", "application/json"),
    ("delete", "/jobs/{job_id}"): ({401, 404, 409, 422}, "200", "application/json"),
    ("put", "/jobs/{job_id}/images/{index}"): ({401, 404, 409, 413, 422, 507}, "200", "application/json"),
    ("put", "/jobs/{job_id}/images"): ({401, 404, 409, 413, 422, 507}, "200", "application/json"),
    ("put", "/jobs/{job_id}/mask"): ({401, 404, 409, 413, 422}, "200", "application/json"),
    ("post", "/jobs/{job_id}/start"): ({401, 404, 409, 422, 429}, "202", "application/json"),
    ("get", "/jobs/{job_id}/results.zip"): ({401, 404, 409, 422, 429}, "200", "application/zip"),
    ("get", "/jobs/{job_id}/results/{name}.npy"): ({401, 404, 409, 413, 422, 429}, "200", NPY),
    ("get", "/jobs/{job_id}/previews/{name}.png"): ({401, 404, 409, 422}, "200", "image/png"),
    ("get", "/health"): (set(), "200", "application/json"),
}


#: Fields of a status body that the CLI, the client, the page and the tests read.
STATUS_FIELDS = {
    *("id", "state", "owner", "created_at", "updated_at", "started_at", "finished_at", "error", "eps"),
    *("tiles_total", "tiles_done", "pixels_total", "pixels_done", "certified_pixels", "solved_pixels"),
    *("pixel_rate", "progress", "warnings", "results", "links", "uploaded", "k", "status_url"),
    "calibration",
}


def _refs(node) -> list[str]:
    if isinstance(node, dict):
        return ([node["$ref"]] if "$ref" in node else []) + [r for v in node.values() for r in _refs(v)]
    if isinstance(node, list):
        return [r for v in node for r in _refs(v)]
    return []


def test_openapi_is_generated_from_the_code_and_typed(server: Server, tmp_path: Path) -> None:
    import httpx

    from maxfs.service.http.app import create_app
    from maxfs.service.results.previews import HTTP_PREVIEWS
    from maxfs.service.settings import Settings
    from maxfs.storage.outputs import OUTPUT_NAMES as OUTPUTS

    live = httpx.get(server.url + "/openapi.json", timeout=30).json()
    assert live == create_app(Settings(data_dir=tmp_path, auth=True)).openapi()  # nothing written by hand

    schemas = live["components"]["schemas"]
    for ref in _refs(live):
        assert ref.startswith("#/components/schemas/") and ref.split("/")[-1] in schemas, ref
    assert "HTTPValidationError" not in schemas and "ValidationError" not in schemas  # not our 422 body
    assert schemas["ErrorBody"]["required"] == ["error", "detail"]
    bearer = live["components"]["securitySchemes"]["bearer"]
    assert (bearer["type"], bearer["scheme"]) == ("http", "bearer")  # Swagger UI's "Authorize"

    ops = {(m, p): op for p, item in live["paths"].items() for m, op in item.items()}
    assert set(ops) == set(OPERATIONS), "an operation was added or removed: document it here"
    for key, (errors, ok, media) in OPERATIONS.items():
        op = ops[key]
        codes = set(op["responses"]) - {ok}
        assert codes == {str(c) for c in errors}, (key, codes)
        for code in codes:
            assert op["responses"][code]["content"] == {
                "application/json": {"schema": {"$ref": "#/components/schemas/ErrorBody"}}
            }, (key, code)
        assert list(op["responses"][ok]["content"]) == [media], key
        assert op.get("security") == ([{"bearer": []}] if key[1].startswith("/jobs") else None), key
        if media == "application/json" and key[1] != "/health":
            schema = op["responses"][ok]["content"][media]["schema"]
            assert schema.get("$ref", schema.get("items", {}).get("$ref")) == "#/components/schemas/JobStatus"

    bodies = {k: list(ops[k]["requestBody"]["content"]) for k in ops if "requestBody" in ops[k]}
    assert bodies == {
        ("post", "/jobs"): ["application/json"],
        ("put", "/jobs/{job_id}/images/{index}"): ["application/octet-stream", "image/png", "image/tiff"],
        ("put", "/jobs/{job_id}/images"): ["application/octet-stream"],
        ("put", "/jobs/{job_id}/mask"): ["application/octet-stream", "image/png"],
    }
    names = {
        key[1]: next(p for p in ops[key]["parameters"] if p["name"] == "name")["schema"]["enum"]
        for key in ops
        if key[1].endswith(("{name}.npy", "{name}.png"))
    }
    assert names == {
        "/jobs/{job_id}/results/{name}.npy": list(OUTPUTS),
        "/jobs/{job_id}/previews/{name}.png": list(HTTP_PREVIEWS),
    }
    # the status model documents the record's fields the clients read, and what status_body adds
    assert STATUS_FIELDS <= set(schemas["JobStatus"]["properties"])


def test_live_bodies_match_the_models(server: Server) -> None:
    import httpx

    from maxfs.service.http.models import ErrorBody, JobStatus

    with MaxfsClient(server.url, server.tokens["alice"]) as alice:
        jid = _job(alice, 16, QUICK, start=True)
        typed = alice.job(jid)  # the client checks the body against JobStatus
        assert typed.id == jid and (typed.k, typed.uploaded) == (8, 8) and typed.state != "created"
        assert jid in {j.id for j in alice.job_list()}
        assert set(alice.status(jid)) >= set(typed.model_fields_set)  # nothing dropped
    bob = {"Authorization": f"Bearer {server.tokens['bob']}"}
    r = httpx.get(f"{server.url}/jobs/{'0' * 32}", headers=bob)
    assert r.status_code == 404 and ErrorBody.model_validate(r.json()).error == "NotFoundError"
    r = httpx.get(f"{server.url}/jobs", headers={"Authorization": f"Bearer {server.tokens['root']}"})
    assert [JobStatus.model_validate(st).owner for st in r.json()]  # the admin's list, every body


def test_docs_pages_name_only_their_own_assets(server: Server) -> None:
    """Without a browser: every ``src``/``href`` of /docs, /redoc and the job page is a path on this
    server that answers 200 (the browser test also watches what the scripts load)."""
    import re

    import httpx

    for page in ("/docs", "/redoc", "/"):
        html = httpx.get(server.url + page, timeout=30).text
        urls = re.findall(r"""(?:src|href)=["']([^"']+)["']""", html) + re.findall(r"url: '([^']+)'", html)
        urls += re.findall(r"""spec-url=["']([^"']+)["']""", html)
        assert urls, page
        for url in urls:
            assert url.startswith("/") and not url.startswith("//"), f"{page} loads {url}"
            assert httpx.get(server.url + url, timeout=30).status_code == 200, f"{page}: {url}"
