"""The inspection page (``GET /inspect``) and what it reads: reference thumbnails stored in
the index, ``/v1/references``, the thumbnail and evidence endpoints; and the page itself in
a real headless Chromium (the system package, driven by Playwright) against a real
``hmpf-serve``.

Without chromium or playwright the browser tests are skipped, with the reason; with
``HMPF_REQUIRE_BROWSER=1`` (set by ``.ci/run``, which installs both: ``make browser``) they
fail instead, so CI cannot pass without running them. ``HMPF_SCREENSHOT=PATH`` saves the
page's screenshot there too (how ``docs/inspect.png`` was made).
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest

from hmpf.config import parse_config
from hmpf.imageio import load_image
from hmpf.index import layout, thumbnails
from hmpf.index.reader import IndexReader
from indexer import maintenance
from indexer.build import add, build, remove
from service.auth import add_key
from tests.conftest import copy_gp, write_positions
from tests.service_helpers import BUILD_OPTIONS, Server

#: GeM + Gist narrow, OLO (the default config's local method) decides with them.
INSPECT_CONFIG = {
    "name": "inspect-test",
    "methods": {"olo": {"regions": 50, "vocabulary_size": 32}},
    "tiers": [{"methods": ["gem", "gist"], "k": 5}, {"methods": ["olo", "gem", "gist"], "k": 1}],
}
#: A quick config for the indexer tests.
GIST = {"name": "gist", "tiers": [{"methods": ["gist"], "k": 1}]}
N_REFS = 30
CHROMIUM = os.environ.get("HMPF_CHROMIUM") or shutil.which("chromium")


@pytest.fixture(scope="module")
def index(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    base = tmp_path_factory.mktemp("inspect")
    refs = copy_gp(gardens_point, "day_right", base / "refs", N_REFS)
    out = base / "index"
    meta = write_positions(refs, base / "meta.csv")
    build(parse_config(INSPECT_CONFIG), refs, out, metadata=meta, options=BUILD_OPTIONS)
    return out


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    path = tmp_path_factory.mktemp("inspect-keys") / "keys.yaml"
    return {"file": str(path), "vehicle": add_key(path, "car", "vehicle")}


@pytest.fixture(scope="module")
def server(index: Path, keys: dict[str, str], tmp_path_factory) -> Iterator[Server]:
    srv = Server(
        index, tmp_path_factory.mktemp("inspect-log") / "serve.log", keys_file=keys["file"]
    )
    yield srv
    srv.stop()
    assert "Traceback" not in srv.output()


def _night(gardens_point: Path, i: int) -> Path:
    return sorted((gardens_point / "night_right").iterdir())[i]


def _day_names(gardens_point: Path) -> list[str]:
    return [p.name for p in sorted((gardens_point / "day_right").iterdir())[:N_REFS]]


def _error(r: httpx.Response, status: int, code: str | None = None) -> dict[str, Any]:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/json"), r.headers
    err: dict[str, Any] = r.json()["error"]
    if code is not None:
        assert err["code"] == code, err
    return err


def _strip_thumbnails(version: Path) -> None:
    """Make ``version`` what a build before thumbnails wrote: format 1.0, no thumbnails."""
    manifest = json.loads((version / layout.MANIFEST).read_text())
    (version / thumbnails.FILE).unlink()
    del manifest["files"][thumbnails.FILE]
    del manifest["thumbnails"]
    manifest["format_version"] = "1.0"
    layout.write_manifest(version, manifest)


# -- thumbnails in the index -------------------------------------------------------------------
def test_build_add_remove_store_each_references_thumbnail(gardens_point, tmp_path) -> None:
    refs = copy_gp(gardens_point, "day_right", tmp_path / "a", 4)
    more = tmp_path / "b"
    more.mkdir()
    for p in sorted((gardens_point / "day_right").iterdir())[4:6]:
        shutil.copy(p, more / p.name)
    root = tmp_path / "index"
    built = build(parse_config(GIST), refs, root, options=BUILD_OPTIONS)
    assert built.bytes_thumbnails > 0 and "thumbnails" in built.lines()[1]
    add(root, more, options=BUILD_OPTIONS)
    gone = sorted(p.name for p in refs.iterdir())[1]
    remove(root, [gone])
    with IndexReader(root) as reader:
        assert gone not in reader.refs.names and reader.n == 5
        for i, name in enumerate(reader.refs.names):
            src = refs / name if (refs / name).exists() else more / name
            stored = reader.thumbnail(i)
            assert stored == thumbnails.make_thumbnail(load_image(src)), name
            img = cv2.imdecode(np.frombuffer(stored, np.uint8), cv2.IMREAD_COLOR)
            assert max(img.shape[:2]) == thumbnails.MAX_SIDE
        entry = reader.manifest["files"][thumbnails.FILE]
        assert reader.manifest["summary"]["bytes_thumbnails"] == entry["bytes"]
    # A damaged thumbnail is caught like any other file: verify names it, readers refuse.
    version = root / layout.current_version(root)  # type: ignore[operator]
    data = bytearray((version / thumbnails.FILE).read_bytes())
    data[-100] ^= 0xFF
    (version / thumbnails.FILE).write_bytes(bytes(data))
    problems = maintenance.verify(root)
    assert any(thumbnails.FILE in p and "sha256" in p for p in problems), problems
    with pytest.raises(layout.IndexCorruptError, match=thumbnails.FILE):
        IndexReader(root)


def test_thumbnails_of_an_interrupted_build_are_reused(gardens_point, tmp_path) -> None:
    """``make_thumbnails`` with a cache (``.build/thumbnails``, keyed by the image's sha256)
    makes each thumbnail once: a resumed build reads the ones made before."""
    from hmpf.features import file_digest

    paths = sorted(copy_gp(gardens_point, "day_right", tmp_path / "a", 2).iterdir())
    digests = [file_digest(p) for p in paths]
    first = thumbnails.make_thumbnails(paths, digests, tmp_path / "cache")
    assert sorted(p.stem for p in (tmp_path / "cache").iterdir()) == sorted(digests)
    marked = thumbnails.make_thumbnail(np.zeros((9, 16, 3), np.uint8))
    (tmp_path / "cache" / f"{digests[1]}.jpg").write_bytes(marked)
    again = thumbnails.make_thumbnails(paths, digests, tmp_path / "cache")
    assert again.item(0).tobytes() == first.item(0).tobytes()
    assert again.item(1).tobytes() == marked


def test_identical_images_share_one_cached_thumbnail(tmp_path) -> None:
    """A route may hold byte-identical frames (Nordland does): they share one cache key, and
    the threads that make them at once must not trip over each other's temporary file (small
    images, so that the threads overlap)."""
    from hmpf.features import file_digest

    folder = tmp_path / "same"
    folder.mkdir()
    paths = []
    for i in range(100):  # 100 frames, each 4 times in a row: 4 threads make each at once
        ok, png = cv2.imencode(".png", np.full((32, 64, 3), i, np.uint8))
        for j in range(4):
            paths.append(folder / f"{i:03d}-{j}.png")
            paths[-1].write_bytes(png.tobytes())
    digests = [file_digest(p) for p in paths]
    made = thumbnails.make_thumbnails(paths, digests, tmp_path / "cache")
    for i in range(0, len(paths), 4):
        assert len({made.item(i + j).tobytes() for j in range(4)}) == 1
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == sorted(
        f"{d}.jpg" for d in set(digests)
    )


def test_a_version_without_thumbnails_loads_and_grows(gardens_point, tmp_path) -> None:
    refs = copy_gp(gardens_point, "day_right", tmp_path / "a", 3)
    root = tmp_path / "index"
    build(parse_config(GIST), refs, root, options=BUILD_OPTIONS)
    _strip_thumbnails(root / "v0001")
    assert maintenance.verify(root) == []
    with IndexReader(root) as reader:
        assert reader.thumbnails is None and reader.thumbnail(0) is None
    manifest = json.loads((root / "v0001" / layout.MANIFEST).read_text())
    manifest["thumbnails"] = {"file": "references.h5x"}  # not a file the manifest covers
    layout.write_manifest(root / "v0001", manifest)
    with pytest.raises(layout.IndexCorruptError, match="not in its files"):
        IndexReader(root)
    del manifest["thumbnails"]
    layout.write_manifest(root / "v0001", manifest)
    more = tmp_path / "b"
    more.mkdir()
    new = sorted((gardens_point / "day_right").iterdir())[3]
    shutil.copy(new, more / new.name)
    add(root, more, options=BUILD_OPTIONS)  # the old rows get empty entries, the new one its own
    with IndexReader(root) as reader:
        assert [reader.thumbnail(i) is not None for i in range(4)] == [False] * 3 + [True]
    remove(root, [new.name])
    with IndexReader(root) as reader:
        assert reader.n == 3 and all(reader.thumbnail(i) is None for i in range(3))


@pytest.fixture(scope="module")
def old_server(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """hmpf-serve (no auth) on an index built before thumbnails (3 references)."""
    base = tmp_path_factory.mktemp("old")
    refs = copy_gp(gardens_point, "day_right", base / "refs", 3)
    build(parse_config(GIST), refs, base / "index", options=BUILD_OPTIONS)
    _strip_thumbnails(base / "index" / "v0001")
    srv = Server(base / "index", base / "serve.log", auth="false")
    yield srv
    srv.stop()


def test_old_index_is_served_without_thumbnails(old_server, gardens_point) -> None:
    listing = httpx.get(old_server.url + "/v1/references").json()
    assert listing["thumbnails"] is False and len(listing["names"]) == 3
    _error(httpx.get(old_server.url + "/v1/references/0/thumbnail"), 404, "no_thumbnail")
    frame = sorted((gardens_point / "day_right").iterdir())[1]
    with frame.open("rb") as fh:
        r = httpx.post(old_server.url + "/v1/localize", files={"image": fh}, timeout=60)
    assert r.status_code == 200 and r.json()["match"]["name"] == frame.name, r.text


def test_page_shows_a_placeholder_without_thumbnails(browser_ready, old_server, gardens_point):
    with _page(old_server.url) as page:
        _use_key(page, "")
        _localise(page, sorted((gardens_point / "day_right").iterdir())[1])
        page.wait_for_selector("#match-thumb.placeholder")
        page.wait_for_function("document.querySelectorAll('.cand img.placeholder').length > 0")
        assert page.is_hidden("#error")
        assert "no evidence image: 409" in page.inner_text("#evidence-caption")


# -- the endpoints -----------------------------------------------------------------------------
def test_page_is_served_without_a_key_and_holds_no_data(server) -> None:
    r = httpx.get(server.url + "/inspect")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert "inspect.js" in r.text and ".jpg" not in r.text
    for name in ("inspect.js", "inspect.css"):
        assert httpx.get(f"{server.url}/inspect/static/{name}").status_code == 200
    assert "/inspect" not in httpx.get(server.url + "/openapi.json").json()["paths"]


def test_data_endpoints_need_a_key(server, keys, gardens_point) -> None:
    frame = _night(gardens_point, 3).read_bytes()
    for key in (None, "not-a-key"):
        headers = {} if key is None else {"X-API-Key": key}
        for r in (
            httpx.get(server.url + "/v1/references", headers=headers),
            httpx.get(server.url + "/v1/references/0/thumbnail", headers=headers),
            httpx.post(
                server.url + "/v1/evidence?reference=0",
                files={"image": ("f.png", frame, "image/png")},
                headers=headers,
            ),
        ):
            _error(r, 401, "unauthorized")


def test_references_and_thumbnails(server, keys, gardens_point) -> None:
    h = {"X-API-Key": keys["vehicle"]}
    listing = httpx.get(server.url + "/v1/references", headers=h).json()
    assert listing["names"] == _day_names(gardens_point) and listing["thumbnails"] is True
    assert listing["lat"][1] > listing["lat"][0] and len(listing["lon"]) == N_REFS
    name = listing["names"][7]
    by_name = httpx.get(f"{server.url}/v1/references/{name}/thumbnail", headers=h)
    by_id = httpx.get(f"{server.url}/v1/references/7/thumbnail", headers=h)
    assert by_name.status_code == 200 and by_name.headers["content-type"] == "image/jpeg"
    assert by_name.content == by_id.content
    img = cv2.imdecode(np.frombuffer(by_name.content, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and max(img.shape[:2]) == thumbnails.MAX_SIDE
    for ref in ("no-such.jpg", str(N_REFS), "-1"):
        _error(httpx.get(f"{server.url}/v1/references/{ref}/thumbnail", headers=h), 404)


def test_evidence_image(server, keys, gardens_point) -> None:
    h = {"X-API-Key": keys["vehicle"]}
    frame = _night(gardens_point, 10)
    name = _day_names(gardens_point)[10]
    with frame.open("rb") as fh:
        r = httpx.post(
            f"{server.url}/v1/evidence", params={"reference": name}, files={"image": fh},
            headers=h, timeout=120,
        )  # fmt: skip
    assert r.status_code == 200 and r.headers["content-type"] == "image/png", r.text
    assert r.headers["x-hmpf-evidence-method"] == "olo"
    assert int(r.headers["x-hmpf-evidence-pairs"]) > 0
    png = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)
    assert png is not None and png.shape[0] == 320 and png.shape[1] > 2 * 320
    assert float(png.std()) > 10


def test_evidence_refuses_bad_input_with_json(server, keys, gardens_point) -> None:
    h = {"X-API-Key": keys["vehicle"]}
    url = server.url + "/v1/evidence"
    ok = _night(gardens_point, 1).read_bytes()
    cases = [
        ({"reference": "0"}, {"image": ("x.jpg", b"not an image", "image/jpeg")}, 422),
        ({"reference": "0"}, {"image": ("x.jpg", b"", "image/jpeg")}, 422),
        ({"reference": "0"}, {"image": ("x.jpg", ok[: len(ok) // 3], "image/jpeg")}, 422),
        ({"reference": "0"}, {"image": ("x.gif", b"GIF89a" + b"\0" * 64, "image/gif")}, 415),
        ({"reference": "0"}, {"other": ("x.jpg", ok, "image/jpeg")}, 422),
        ({}, {"image": ("x.jpg", ok, "image/jpeg")}, 422),
        ({"reference": "nope"}, {"image": ("x.jpg", ok, "image/jpeg")}, 404),
    ]
    for params, files, status in cases:
        _error(httpx.post(url, params=params, files=files, headers=h, timeout=60), status)
    raw = httpx.post(
        url, params={"reference": "0"}, content=ok, headers={**h, "Content-Type": "image/jpeg"}
    )
    assert 400 <= raw.status_code < 500 and "error" in raw.json(), raw.text


# -- the page in a real browser --------------------------------------------------------------
def _browser_missing() -> str | None:
    """Why the browser tests cannot run here (None: they can)."""
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "playwright is not installed (pip install -e '.[dev]')"
    if CHROMIUM is None:
        return "no chromium on PATH (make browser: apt-get install chromium)"
    return None


@pytest.fixture
def browser_ready() -> None:
    why = _browser_missing()
    if why is not None:
        if os.environ.get("HMPF_REQUIRE_BROWSER") == "1":
            pytest.fail(f"HMPF_REQUIRE_BROWSER=1 but {why}")
        pytest.skip(why)


class _page:
    """A headless Chromium page on ``url/inspect`` (closed on exit)."""

    def __init__(self, url: str) -> None:
        self.url = url

    def __enter__(self) -> Any:
        from playwright.sync_api import sync_playwright

        self._pw = sync_playwright().start()
        self._browser = self._pw.chromium.launch(executable_path=CHROMIUM, headless=True)
        page = self._browser.new_page(viewport={"width": 1280, "height": 1400})
        page.set_default_timeout(120_000)
        page.goto(self.url + "/inspect")
        return page

    def __exit__(self, *exc: object) -> None:
        self._browser.close()
        self._pw.stop()


def _use_key(page: Any, key: str) -> None:
    page.fill("#key", key)
    page.click("#key-form button")


def _localise(page: Any, frame: Path) -> None:
    before = int(page.evaluate("Number(document.body.dataset.answered || 0)"))
    page.wait_for_selector("#go:not([disabled])")
    page.set_input_files("#image", str(frame))
    page.click("#go")
    page.wait_for_function(f"Number(document.body.dataset.answered || 0) > {before}")


def test_page_answers_a_night_frame_in_chromium(
    browser_ready, server, keys, gardens_point, tmp_path
) -> None:
    names = _day_names(gardens_point)
    with _page(server.url) as page:
        _use_key(page, "wrong-key")
        page.wait_for_selector("#error:not([hidden])")
        assert "401" in page.inner_text("#error") and page.is_disabled("#go")

        _use_key(page, keys["vehicle"])
        page.wait_for_selector("#error", state="hidden")
        assert f"{N_REFS} references" in page.inner_text("#index-info")
        page.fill("#vehicle", "car-17")
        for i in (10, 11, 12):  # sequence mode: the page carries the track
            _localise(page, _night(gardens_point, i))
        fields = page.inner_text("#answer-fields")
        assert "accepted" in fields and "decided by" in fields and "sequence" in fields
        match = page.inner_text("#match-caption").removeprefix("reference ")
        assert abs(names.index(match) - 12) <= 2, match  # the right place, +-2 frames
        images = "#query-img, #match-thumb, #evidence, .cand img"
        page.wait_for_function(
            f"[...document.querySelectorAll('{images}')].every(i => i.complete && i.naturalWidth)"
        )
        widths = page.eval_on_selector_all(images, "els => els.map(e => e.naturalWidth)")
        assert len(widths) >= 4 and all(w > 0 for w in widths), widths
        assert page.locator(".tier").count() == 3  # two tiers and the final ranking
        assert page.locator(".bar i").count() >= 3
        assert page.locator("#plot-positions circle").count() >= N_REFS + 1
        assert page.locator("#plot-positions circle[fill='#d33']").count() == 1
        assert page.locator("#plot-belief circle").count() >= 3
        shot = page.screenshot(full_page=True)
    img = cv2.imdecode(np.frombuffer(shot, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[0] > 600
    assert float(img.std()) > 20, "the screenshot is blank"
    (tmp_path / "inspect.png").write_bytes(shot)
    if os.environ.get("HMPF_SCREENSHOT"):
        Path(os.environ["HMPF_SCREENSHOT"]).write_bytes(shot)


def test_api_docs_load_with_the_network_off(browser_ready, server) -> None:
    """/docs (Swagger UI) and /redoc render the API from the service alone: every request to
    another host is refused by the browser. /docs tries none; ReDoc's bundle hard-codes one
    decorative image (its vendor's logo in the sidebar footer), the only one it may try."""
    from playwright.sync_api import sync_playwright

    local = server.url.rstrip("/")
    elsewhere: list[str] = []

    def only_local(route: Any) -> None:
        if route.request.url.startswith(local + "/"):
            route.continue_()
        else:
            elsewhere.append(route.request.url)
            route.abort()

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True)
        try:
            page = browser.new_page()
            page.set_default_timeout(60_000)
            page.route("**/*", only_local)
            page.goto(local + "/docs")
            page.wait_for_selector(".swagger-ui .info .title")
            assert "hmpf" in page.inner_text(".swagger-ui .info .title")
            page.wait_for_selector("#operations-localize-localize_v1_localize_post")
            assert elsewhere == [], elsewhere
            page.goto(local + "/redoc")
            page.wait_for_selector("h1")
            assert "hmpf" in page.inner_text("h1")
            page.wait_for_selector('text="/v1/localize"')
        finally:
            browser.close()
    assert set(elsewhere) <= {"https://cdn.redoc.ly/redoc/logo-mini.svg"}, elsewhere


def test_kaze_evidence_draws_keypoint_pairs(gardens_point, tmp_path) -> None:
    """With KAZE in the index the evidence is its keypoint pairs (stored reference
    keypoints against the query's), rendered without a server (a query thread's work)."""
    from service.evidence import evidence_method, render_evidence

    refs = copy_gp(gardens_point, "day_right", tmp_path / "refs", 4)
    kaze = {"name": "kaze", "tiers": [{"methods": ["gist"], "k": 2}, {"methods": ["kaze"], "k": 1}]}
    build(parse_config(kaze), refs, tmp_path / "index", options=BUILD_OPTIONS)
    with IndexReader(tmp_path / "index") as reader:
        assert evidence_method(reader) == "kaze"
        query = load_image(_night(gardens_point, 2))
        out = render_evidence(reader, query, 2, reader.thumbnail(2))  # type: ignore[arg-type]
    assert out.method == "kaze" and out.pairs > 0
    png = cv2.imdecode(np.frombuffer(out.png, np.uint8), cv2.IMREAD_COLOR)
    assert png is not None and png.shape[0] == 320
