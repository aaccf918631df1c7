"""The browser viewer in a real headless Chromium (Playwright, system Chromium; never
``playwright install``), served from the checkout with the kernels the suite compiled, at the
size of a laptop screen (1440 x 900). (The installed wheel serving its viewer, WebSocket and
MJPEG is tests/test_packaging.py's; a wheel's venv would compile every kernel again, numba's
cache being keyed by each module's path: about 95 s of this test's waits.)

What a user does is what the test does: frames arrive; the live figures update; a method is
picked and applies by itself; a preset fills the form; a parameter change applies as typed;
two bad fields each show their own error; masks toggle (and with ``m``); the heat map; the
compare view reaches the same step on a paused replay, whichever method looks further ahead;
a snapshot saves PNGs that carry the method, the step and the parameters; on a phone the
controls sit under the picture and the compare labels do not overlap; ``/docs`` renders with
every request off the machine refused.

The screenshots in the docs come from here: ``CFSR_SCREENSHOT_DIR=docs/img pytest
tests/test_viewer.py`` rewrites ``docs/img/viewer*.png`` (without it they go to a temporary
folder), so they show the viewer as it is.
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import zlib
from pathlib import Path

import pytest
from conftest import require_tier
from livehelpers import LiveServer, write_pattern

CHROMIUM = os.environ.get("CFSR_CHROMIUM", "/usr/bin/chromium")
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]
VIEWPORT = {"width": 1440, "height": 900}

HASH_JS = """() => {
  const c = document.getElementById('frame');
  const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
  let h = 2166136261;
  for (let i = 0; i < d.length; i += 1) { h ^= d[i]; h = Math.imul(h, 16777619) >>> 0; }
  return h;
}"""


def png_text(data: bytes) -> dict[str, str]:
    """The tEXt chunks of a PNG (keyword -> text), after checking every chunk's CRC."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
    out, o = {}, 8
    while o < len(data):
        (n,) = struct.unpack(">I", data[o:o + 4])
        kind, body = data[o + 4:o + 8], data[o + 8:o + 8 + n]
        (crc,) = struct.unpack(">I", data[o + 8 + n:o + 12 + n])
        assert zlib.crc32(kind + body) == crc, f"bad CRC in {kind!r}"
        if kind == b"tEXt":
            k, _, v = body.partition(b"\0")
            out[k.decode("latin-1")] = v.decode("latin-1")
        o += 12 + n
    return out


def test_png_text_reads_chunks_and_checks_crcs():
    """The reader the snapshot check relies on: finds tEXt chunks, refuses a bad CRC."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(
            ">I", zlib.crc32(kind + body))

    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", b"\0" * 13) + chunk(b"tEXt", b"step\x0042") \
        + chunk(b"IEND", b"")
    assert png_text(png) == {"step": "42"}
    bad = bytearray(png)
    bad[-20] ^= 1  # a byte of the tEXt body
    with pytest.raises(AssertionError, match="CRC"):
        png_text(bytes(bad))


@pytest.fixture(scope="module")
def browser():
    try:
        from playwright.sync_api import sync_playwright
    except ImportError as exc:
        require_tier("browser", False, f"python playwright is not installed ({exc})")
    exe = CHROMIUM if os.path.exists(CHROMIUM) else shutil.which("chromium")
    require_tier("browser", bool(exe), f"no Chromium at {CHROMIUM} (apt-get install chromium)")
    pw = sync_playwright().start()
    try:
        b = pw.chromium.launch(executable_path=exe, args=ARGS)
    except Exception as exc:  # noqa: BLE001
        pw.stop()
        require_tier("browser", False, f"Chromium did not start: {exc}")
    yield b
    b.close()
    pw.stop()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """``cfsr serve`` with no source: its built-in demo (the simulated rotating disk), made in
    a cache folder of its own."""
    d = tmp_path_factory.mktemp("viewer")
    with LiveServer(["--data-dir", str(d / "data")], cwd=d,
                    env={"CFSR_CACHE_DIR": str(d / "cache")}) as s:
        yield s


def _shots(tmp_path: Path) -> Path:
    shots = Path(os.environ.get("CFSR_SCREENSHOT_DIR", tmp_path))
    shots.mkdir(parents=True, exist_ok=True)
    return shots


def _wait(page, js, timeout=60_000, arg=None):
    page.wait_for_function(js, arg=arg, timeout=timeout)


# True (as {hash}) once the picture's hash is the same at two polls in a row: called by
# Playwright's wait_for_function every STABLE_POLL_MS, the page keeps the previous hash
STABLE_JS = "() => {\n  const h = (" + HASH_JS + """)();
  const prev = window.__cfsrLastHash;
  window.__cfsrLastHash = h;
  return prev === h ? { hash: h } : false;
}"""
STABLE_POLL_MS = 250


def _stable_hash(page, timeout=10_000):
    """The picture's hash once it stopped changing (the replay is paused: a new method's
    first frames may still be on their way)."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    page.evaluate("() => { window.__cfsrLastHash = undefined; }")
    try:
        h = page.wait_for_function(STABLE_JS, polling=STABLE_POLL_MS, timeout=timeout)
    except PlaywrightTimeout:
        raise AssertionError("the picture never settled") from None
    return h.json_value()["hash"]


def _pick_method(page, name, timeout=300_000):
    """Choose a method in the menu, nothing else: it applies by itself."""
    drawn = page.evaluate("window.cfsrViewer.drawn")
    page.select_option("#method-select", name)
    _wait(page, "(m) => window.cfsrViewer.method === m", arg=name, timeout=timeout)
    _wait(page, "(n) => window.cfsrViewer.drawn > n", arg=drawn)


def _compare_on_one_step(page, method: str) -> int:
    """Pin the frame shown, pick ``method``: on the paused replay the live side reaches the
    pinned step, whichever of the two methods looks further ahead. Returns that step."""
    from playwright.sync_api import expect

    page.click("#compare")
    _wait(page, "() => window.cfsrViewer.compare && window.cfsrViewer.pinned")
    pinned = page.evaluate("window.cfsrViewer.pinned.frame.step")
    _pick_method(page, method)
    _wait(page, "([m, s]) => window.cfsrViewer.method === m && window.cfsrViewer.step === s",
          arg=[method, pinned], timeout=120_000)
    expect(page.locator("#compare-msg")).to_contain_text("same step")
    return pinned


def _key(page, key):
    """A key press as a user makes it: on the page, not inside a form field."""
    page.evaluate("() => document.activeElement && document.activeElement.blur()")
    page.keyboard.press(key)


def _server_params(server) -> dict:
    return server.get("/api/config").json()["params"]


@pytest.mark.browser
@pytest.mark.timeout(900)
def test_viewer_in_chromium(browser, server, tmp_path):
    from playwright.sync_api import expect

    shots = _shots(tmp_path)
    page = browser.new_page(viewport=VIEWPORT, accept_downloads=True)
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(server.url + "/")
    assert page.title() == "CFSR live viewer"

    # frames arrive and change
    _wait(page, "() => window.cfsrViewer && window.cfsrViewer.frames >= 3")
    s0 = page.evaluate("window.cfsrViewer.step")
    _wait(page, "(s) => window.cfsrViewer.step !== s && window.cfsrViewer.drawn > 3", arg=s0)
    assert page.inner_text("#conn") == "live"
    assert page.inner_text("#frame-method") == "tfp"

    # the picture fills the space it has: wider than the 400 px frame, and the live figures
    # are on the first screen, beside it
    box = page.locator("#frame").bounding_box()
    assert box["width"] > 2 * 400 and box["y"] + box["height"] <= VIEWPORT["height"]
    fig = page.locator("#figures").bounding_box()
    assert fig["y"] + fig["height"] <= VIEWPORT["height"], "live figures below the fold"

    # live figures update; every drop counter says whether spike data was lost
    _wait(page, "() => window.cfsrViewer.statusUpdates >= 2")
    n_status = page.evaluate("window.cfsrViewer.statusUpdates")
    _wait(page, "(n) => window.cfsrViewer.statusUpdates > n", arg=n_status)
    assert float(page.inner_text("#fig-input").replace(",", "")) > 0
    assert float(page.inner_text("#fig-rtf")) > 0
    assert page.inner_text("#drop-ring") != "-"
    for title in page.eval_on_selector_all(".drop", "els => els.map(e => e.title)"):
        assert "No spike data lost" in title or "Spike data WAS lost" in title, title

    # the form's bounds come from GET /api/limits (the rules are written once, in the service)
    from cfsr_live.service.settings import MAX_FPS_RANGE

    assert float(page.get_attribute("#max-fps", "max")) == MAX_FPS_RANGE[1]
    assert float(page.get_attribute("#max-fps", "min")) == MAX_FPS_RANGE[0]
    valid = "() => document.getElementById('record-name').checkValidity()"
    page.fill("#record-name", "../escape")
    assert page.evaluate(valid) is False
    page.click("#record")
    assert "not a recording name" in page.inner_text("#record-msg")
    page.fill("#record-name", "take-1.v2")
    assert page.evaluate(valid) is True
    expect(page.locator("#record-msg")).to_have_text("")
    page.fill("#record-name", "")

    # pause the replay (space) so the picture only changes when we change something
    _key(page, " ")
    _wait(page, "() => window.cfsrViewer.lastStatus && "
                "window.cfsrViewer.lastStatus.source.replay.playing === false")
    h_tfp = _stable_hash(page)

    # picking a method applies it, with no button
    _pick_method(page, "tfi")
    assert _stable_hash(page) != h_tfp
    assert page.inner_text("#frame-method") == "tfi"

    # CSR: the presets the library knows, first; choosing one fills the form and applies it
    _pick_method(page, "csr")
    methods = page.evaluate("window.cfsrViewer.methods")
    paper = methods["csr"]["presets"]["paper"]
    options = page.eval_on_selector_all("#preset-select option", "os => os.map(o => o.value)")
    assert {"defaults", *methods["csr"]["presets"]} <= set(options)
    applied = page.evaluate("window.cfsrViewer.applied")
    page.select_option("#preset-select", "paper")
    _wait(page, "(n) => window.cfsrViewer.applied > n", arg=applied)
    assert {k: _server_params(server)[k] for k in paper} == paper
    assert page.input_value("#param-T") == str(paper["T"])

    # a parameter change applies as it is typed (debounced), and the form says "custom";
    # theta is in a collapsed group, opened as a user would
    page.click("details.group:has(#param-theta) summary")
    applied = page.evaluate("window.cfsrViewer.applied")
    page.fill("#param-theta", "9")
    _wait(page, "(n) => window.cfsrViewer.applied > n", arg=applied)
    assert _server_params(server)["theta"] == 9
    assert page.input_value("#preset-select") == "custom"

    # two bad fields: each shows its own error beside it, and nothing is sent
    theta_max = methods["csr"]["params"]["theta"]["maximum"]
    page.fill("#param-theta", str(theta_max + 1))
    page.fill("#max-fps", str(MAX_FPS_RANGE[1] * 10))
    expect(page.locator("#err-param-theta")).to_contain_text(f"<= {theta_max:g}")
    expect(page.locator("#err-max_fps")).to_contain_text(f"<= {MAX_FPS_RANGE[1]:g}")
    expect(page.locator("#config-msg")).to_contain_text("not sent")
    assert _server_params(server)["theta"] == 9
    # a value only the service can refuse (theta counts ISI values: an integer) comes back
    # as the service's message, beside the field it names
    page.fill("#max-fps", "30")
    page.fill("#param-theta", "7.5")
    expect(page.locator("#err-param-theta")).to_contain_text("int", timeout=30_000)
    expect(page.locator("#err-max_fps")).to_have_text("")
    applied = page.evaluate("window.cfsrViewer.applied")
    page.fill("#param-theta", "9")
    _wait(page, "(n) => window.cfsrViewer.applied > n", arg=applied)
    expect(page.locator("#err-param-theta")).to_have_text("")

    # a mask overlay toggles (checkbox and the m key); the mask has its own colour
    _wait(page, "() => window.cfsrViewer.masks.includes('coarse')")
    for _ in range(40):
        if page.evaluate("window.cfsrViewer.maskPixels.coarse") > 0:
            break
        drawn = page.evaluate("window.cfsrViewer.drawn")
        page.click("#step")
        _wait(page, "(n) => window.cfsrViewer.drawn > n", arg=drawn)
    assert page.evaluate("window.cfsrViewer.maskPixels.coarse") > 0, "no dynamic pixels found"
    h_plain = _stable_hash(page)
    drawn = page.evaluate("window.cfsrViewer.drawn")
    _key(page, "m")
    _wait(page, "(n) => window.cfsrViewer.drawn > n", arg=drawn)
    assert page.is_checked("#ov-coarse")
    h_mask = page.evaluate(HASH_JS)
    assert h_mask != h_plain, "the coarse overlay did not change the picture"
    drawn = page.evaluate("window.cfsrViewer.drawn")
    page.uncheck("#ov-coarse")
    _wait(page, "(n) => window.cfsrViewer.drawn > n", arg=drawn)
    assert page.evaluate(HASH_JS) == h_plain

    # the spike-rate heat map, with its scale
    drawn = page.evaluate("window.cfsrViewer.drawn")
    page.check("input[name=view][value=heat]")
    _wait(page, "(n) => window.cfsrViewer.drawn > n", arg=drawn)
    assert page.evaluate(HASH_JS) != h_plain
    assert page.is_visible("#legend")
    page.check("input[name=view][value=gray]")

    # compare: pin TFP, pick CSR; on the paused replay both sides reach the same step
    _pick_method(page, "tfp")
    pinned = _compare_on_one_step(page, "csr")
    expect(page.locator("#label-a")).to_contain_text(f"tfp @ step {pinned}")
    page.check("#ov-coarse")
    page.fill("#split", "50")
    page.dispatch_event("#split", "input")
    page.wait_for_timeout(300)
    page.screenshot(path=str(shots / "viewer-compare.png"))

    # snapshot: the frame and its masks as PNG, method and step in the name, parameters inside
    with page.expect_download() as first:
        page.click("#snapshot")
    _wait(page, "() => window.cfsrViewer.lastSnapshot !== null")
    names = page.evaluate("window.cfsrViewer.lastSnapshot.names")
    assert names[0] == first.value.suggested_filename == f"cfsr-csr-step{pinned}.png"
    text = png_text(Path(first.value.path()).read_bytes())
    assert text["method"] == "csr" and text["step"] == str(pinned)
    assert json.loads(text["parameters"]) == _server_params(server)
    assert names[1].endswith("-masks.png") and "coarse" in text["masks"]
    page.click("#compare-close")

    # the other order: pin CSR, pick TFP, whose frame would come later from the same data (it
    # looks less far ahead): the service holds the pinned step, so both sides show one step
    _compare_on_one_step(page, "tfp")
    page.click("#compare-close")


    # CFSR: its parameters grouped and collapsed, choices as menus, the quality tier when the
    # method has one; its first frame may wait on the compiler (the page says so)
    _pick_method(page, "cfsr", timeout=600_000)
    cfsr = methods["cfsr"]["params"]
    shown = page.eval_on_selector_all("#params-form .param", "els => els.map(e => e.name)")
    assert 0 < len(shown) <= 8 < len(cfsr)
    groups = page.eval_on_selector_all("details.group", "ds => ds.map(d => d.open)")
    assert groups and not any(groups), "the groups should start collapsed"
    for name, p in cfsr.items():
        if p["choices"] and name != "quality":
            assert page.evaluate("(n) => document.getElementById('param-' + n).tagName",
                                 name) == "SELECT", name
    if "quality" in cfsr:
        q = page.eval_on_selector_all("#quality-select option", "os => os.map(o => o.value)")
        assert {"auto", *cfsr["quality"]["choices"]} <= set(q)
    # the docs' picture: the reconstruction itself (the masks are in the compare shot)
    page.evaluate("() => { for (const id of ['ov-coarse', 'ov-fine']) {"
                  " const b = document.getElementById(id); b.checked = false;"
                  " b.dispatchEvent(new Event('change')); } }")
    page.click("details.group summary")
    _wait(page, "(m) => window.cfsrViewer.method === m && "
                "document.getElementById('compile-note').classList.contains('hidden')",
          arg="cfsr")

    # play again: frames move on, and the docs' picture is the product streaming, its output
    # rate the one this page receives
    page.click("#play")
    s1 = page.evaluate("window.cfsrViewer.step")
    _wait(page, "(s) => window.cfsrViewer.step > s", arg=s1, timeout=120_000)
    n_status = page.evaluate("window.cfsrViewer.statusUpdates")
    _wait(page, "(n) => window.cfsrViewer.statusUpdates > n + 2", arg=n_status)
    assert float(page.inner_text("#fig-fps")) > 0, "output rate 0 while frames arrive"
    page.screenshot(path=str(shots / "viewer.png"))
    assert not errors, errors
    page.close()


@pytest.mark.browser
@pytest.mark.timeout(900)
def test_viewer_on_a_phone(browser, server, tmp_path):
    """At 390 x 844: the method menu sits under the picture (not below the figures), and the
    compare view's two labels do not overlap."""
    page = browser.new_page(viewport={"width": 390, "height": 844})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(server.url + "/")
    _wait(page, "() => window.cfsrViewer && window.cfsrViewer.frames >= 3")
    frame = page.locator("#frame").bounding_box()
    menu = page.locator("#method-select").bounding_box()
    figures = page.locator("#figures").bounding_box()
    assert menu["y"] < figures["y"], "the method menu is below the live figures"
    assert menu["y"] - (frame["y"] + frame["height"]) < 300, (frame, menu)
    page.click("#compare")
    _wait(page, "() => window.cfsrViewer.compare && window.cfsrViewer.pinned")
    _wait(page, "() => !document.getElementById('label-b').classList.contains('hidden')"
                " && document.getElementById('label-b').textContent !== ''")
    a, b = (page.locator(f"#label-{k}").bounding_box() for k in "ab")
    assert a["x"] + a["width"] <= b["x"] or a["y"] + a["height"] <= b["y"], (a, b)
    page.screenshot(path=str(_shots(tmp_path) / "viewer-phone.png"))
    page.click("#compare-close")
    assert not errors, errors
    page.close()


@pytest.mark.browser
@pytest.mark.timeout(900)
def test_api_docs_work_offline(browser, server, tmp_path):
    """/docs (Swagger UI) and /redoc render with every request that leaves the machine
    refused, and none is even asked for: their scripts, styles and fonts come from the
    installed packages, and the pages' policy refuses what still points outside."""
    context = browser.new_context(viewport=VIEWPORT)
    outside: list[str] = []

    def only_local(route):
        url = route.request.url
        if url.startswith(server.url) or url.startswith("data:"):
            return route.continue_()
        # none at all: ReDoc's footer logo (from a CDN) is refused by the pages' own policy
        # before it is asked for
        outside.append(url)
        return route.abort()

    context.route("**/*", only_local)  # every page of the context, the docs' popup too
    page = context.new_page()
    page.goto(server.url + "/")
    with page.expect_popup() as popup:
        page.click("a.docs")
    docs = popup.value
    docs.wait_for_selector(".swagger-ui .info .title", timeout=60_000)
    assert "CFSR live" in docs.inner_text(".swagger-ui .info .title")
    docs.wait_for_selector(".opblock", timeout=30_000)
    assert docs.locator(".opblock").count() >= 10
    docs.screenshot(path=str(_shots(tmp_path) / "api-docs.png"))
    page.goto(server.url + "/redoc")
    # ReDoc renders the spec with its own script: the operation's summary appears in the page
    page.get_by_text("switch method / parameters / display scaling").first.wait_for(
        state="attached", timeout=60_000)
    assert not outside, outside
    context.close()


@pytest.mark.browser
@pytest.mark.timeout(900)
def test_viewer_asks_for_the_token_once(browser, tmp_path):
    """With a token, the page asks for it, trades it for a session cookie and streams; the token
    is in no URL the page opens and in nothing the server prints."""
    dat = write_pattern(tmp_path / "data" / "pattern.dat", 3000)
    token = "tok-" + os.urandom(6).hex()
    with LiveServer(["--replay", str(dat), "--data-dir", str(tmp_path / "data"),
                     "--token", token], token=token, cwd=tmp_path) as s:
        page = browser.new_page()
        urls: list[str] = []
        page.on("request", lambda r: urls.append(r.url))
        page.on("websocket", lambda w: urls.append(w.url))
        page.goto(s.url + "/")
        page.wait_for_selector("#login:not(.hidden)")
        page.fill("#login-token", "wrong")
        page.click("#login-form button")
        _wait(page, "() => document.getElementById('login-msg').textContent === 'wrong token'")
        page.fill("#login-token", token)
        page.click("#login-form button")
        _wait(page, "() => window.cfsrViewer.frames >= 2")
        _wait(page, "() => window.cfsrViewer.statusUpdates >= 1")
        assert page.inner_text("#conn") == "live"
        cookies = page.context.cookies()
        assert [c["httpOnly"] for c in cookies if c["name"] == "cfsr_session"] == [True]
        page.close()
        out = s.output()
    assert urls and not any(token in u for u in urls)
    assert token not in out
