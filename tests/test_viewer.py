"""The browser viewer in a real headless Chromium (Playwright, system Chromium; never
``playwright install``), served by the installed wheel (not the checkout): the page loads,
frames change, switching the method changes the picture, a mask overlay toggles, the heat map
shows, and the live figures update."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from conftest import require_tier
from livehelpers import LiveServer, write_pattern
from wheelenv import clean_env

pytestmark = [pytest.mark.browser, pytest.mark.timeout(600)]

CHROMIUM = os.environ.get("CFSR_CHROMIUM", "/usr/bin/chromium")
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]

HASH_JS = """() => {
  const c = document.getElementById('frame');
  const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
  let h = 2166136261;
  for (let i = 0; i < d.length; i += 1) { h ^= d[i]; h = Math.imul(h, 16777619) >>> 0; }
  return h;
}"""


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
def server(tmp_path_factory, live_install):
    """The service as a user gets it: the installed wheel's ``cfsr serve`` (``cfsr[live]`` in a
    fresh venv), started from a folder that is not the checkout."""
    d = tmp_path_factory.mktemp("viewer")
    dat = write_pattern(d / "data" / "pattern.dat", 4000)
    with LiveServer(["--replay", str(dat), "--data-dir", str(d / "data")],
                    command=[str(live_install / "cfsr"), "serve"], cwd=d,
                    env=clean_env(live_install)) as s:
        yield s


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
    """The picture's hash once it stopped changing (the replay is paused: frames of the same
    data still arrive, and a new method's first frames may still be on their way)."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    page.evaluate("() => { window.__cfsrLastHash = undefined; }")
    try:
        h = page.wait_for_function(STABLE_JS, polling=STABLE_POLL_MS, timeout=timeout)
    except PlaywrightTimeout:
        raise AssertionError("the picture never settled") from None
    return h.json_value()["hash"]


def _switch_method(page, name):
    drawn = page.evaluate("window.cfsrViewer.drawn")
    page.select_option("#method-select", name)
    page.click("#apply-config")
    _wait(page, "(m) => window.cfsrViewer.method === m", arg=name, timeout=180_000)
    _wait(page, "(n) => window.cfsrViewer.drawn > n", arg=drawn)


def test_viewer_in_chromium(browser, server, tmp_path):
    shots = Path(os.environ.get("CFSR_SCREENSHOT_DIR", tmp_path))
    shots.mkdir(parents=True, exist_ok=True)
    page = browser.new_page(viewport={"width": 1320, "height": 960})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(server.url + "/")
    assert page.title() == "CFSR live viewer"

    # frames arrive and change
    _wait(page, "() => window.cfsrViewer && window.cfsrViewer.frames >= 3")
    s0 = page.evaluate("window.cfsrViewer.step")
    h0 = page.evaluate(HASH_JS)
    _wait(page, "(s) => window.cfsrViewer.step !== s && window.cfsrViewer.drawn > 3", arg=s0)
    assert page.evaluate(HASH_JS) != h0 or page.evaluate("window.cfsrViewer.step") != s0
    assert page.inner_text("#conn") == "live"
    assert page.inner_text("#frame-method") == "tfp"

    # live figures update
    _wait(page, "() => window.cfsrViewer.statusUpdates >= 2")
    n_status = page.evaluate("window.cfsrViewer.statusUpdates")
    _wait(page, "(n) => window.cfsrViewer.statusUpdates > n", arg=n_status)
    assert float(page.inner_text("#fig-input").replace(",", "")) > 0
    assert float(page.inner_text("#fig-rtf")) > 0
    assert page.inner_text("#drop-ring") != "-"

    # the form's bounds come from GET /api/limits (the rules are written once, in the service)
    from service.settings import MAX_FPS_RANGE

    assert float(page.get_attribute("#max-fps", "max")) == MAX_FPS_RANGE[1]
    assert float(page.get_attribute("#max-fps", "min")) == MAX_FPS_RANGE[0]
    valid = "() => document.getElementById('record-name').checkValidity()"
    page.fill("#record-name", "../escape")
    assert page.evaluate(valid) is False
    page.click("#record")
    assert "not a recording name" in page.inner_text("#record-msg")
    page.fill("#record-name", "take-1.v2")
    assert page.evaluate(valid) is True
    page.fill("#record-name", "")
    page.screenshot(path=str(shots / "viewer-live.png"), full_page=True)

    # pause the replay so the picture only changes when we change something
    page.click("#pause")
    _wait(page, "() => window.cfsrViewer.lastStatus && "
                "window.cfsrViewer.lastStatus.source.replay.playing === false")
    h_tfp = _stable_hash(page)

    # switching the method changes the picture
    _switch_method(page, "tfi")
    h_tfi = _stable_hash(page)
    assert h_tfi != h_tfp
    assert page.inner_text("#frame-method") == "tfi"

    # a mask overlay toggles
    methods = page.evaluate("window.cfsrViewer.methods")
    with_mask = [n for n, m in methods.items() if "coarse" in m["masks"]]
    assert with_mask, "no registered method produces a coarse mask"
    name = "csr" if "csr" in with_mask else with_mask[0]
    _switch_method(page, name)
    _wait(page, "() => window.cfsrViewer.masks.includes('coarse')")
    # the paused frame must have some dynamic pixels for the overlay to show: step the replay
    # (256 frames at a time) until the newest frame has a non-empty coarse mask
    for _ in range(40):
        if page.evaluate("window.cfsrViewer.maskPixels.coarse") > 0:
            break
        drawn = page.evaluate("window.cfsrViewer.drawn")
        page.click("#step")
        _wait(page, "(n) => window.cfsrViewer.drawn > n", arg=drawn)
    assert page.evaluate("window.cfsrViewer.maskPixels.coarse") > 0, "no dynamic pixels found"
    h_plain = _stable_hash(page)
    drawn = page.evaluate("window.cfsrViewer.drawn")
    page.check("#ov-coarse")
    _wait(page, "(n) => window.cfsrViewer.drawn > n", arg=drawn)
    h_mask = page.evaluate(HASH_JS)
    assert h_mask != h_plain, "the coarse overlay did not change the picture"
    page.screenshot(path=str(shots / "viewer-mask.png"), full_page=True)
    drawn = page.evaluate("window.cfsrViewer.drawn")
    page.uncheck("#ov-coarse")
    _wait(page, "(n) => window.cfsrViewer.drawn > n", arg=drawn)
    assert page.evaluate(HASH_JS) == h_plain

    # the spike-rate heat map
    drawn = page.evaluate("window.cfsrViewer.drawn")
    page.check("input[name=view][value=heat]")
    _wait(page, "(n) => window.cfsrViewer.drawn > n", arg=drawn)
    assert page.evaluate(HASH_JS) != h_plain
    assert page.is_visible("#legend")

    # play again: frames move on
    page.check("#ov-coarse")
    page.click("#play")
    s1 = page.evaluate("window.cfsrViewer.step")
    _wait(page, "(s) => window.cfsrViewer.step > s", arg=s1)
    drawn = page.evaluate("window.cfsrViewer.drawn")
    _wait(page, "(n) => window.cfsrViewer.drawn >= n + 5", arg=drawn)  # a few for the shot
    page.screenshot(path=str(shots / "viewer-heat-mask.png"), full_page=True)
    assert not errors, errors
    page.close()


def test_viewer_asks_for_the_token_once(browser, live_install, tmp_path):
    """With a token, the page asks for it, trades it for a session cookie and streams; the token
    is in no URL the page opens and in nothing the server prints."""
    dat = write_pattern(tmp_path / "data" / "pattern.dat", 3000)
    token = "tok-" + os.urandom(6).hex()
    with LiveServer(["--replay", str(dat), "--data-dir", str(tmp_path / "data"),
                     "--token", token], token=token,
                    command=[str(live_install / "cfsr"), "serve"], cwd=tmp_path,
                    env=clean_env(live_install)) as s:
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
