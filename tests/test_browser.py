"""The live view in a real browser: Debian's headless Chromium driven by Playwright.

``mtcw run`` (simulator, one worker, API; every port free) on a small scene; the page at ``/``
must load without console errors, update within seconds, show the same range as
``/v1/points/latest``, and measure its own trigger-to-pixel latency. Artefacts (a screenshot and
the latencies) go to ``out/browser/``. Skipped, saying why, where Chromium or Playwright is
missing (``make test`` installs Debian's ``chromium`` where it runs as root with apt).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import pytest

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "out" / "browser"
#: Chromium's flags for this machine's closed network (else it retries outside addresses many at a time)
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
SCENE = """name = "browser"
description = "static target at 1.7 m, 3 tones, 2^16 samples"
seed = 2
[modulator]
tones = [{ frequency_hz = 500e6 }, { frequency_hz = 700e6 }, { frequency_hz = 950e6 }]
[[targets]]
range_m = 1.7
loss_db = 20.0
[noise]
shot = true
thermal = true
[digitizer]
samples = 65536
[frames]
count = 10
rate_hz = 10
"""


def chromium_path() -> str | None:
    for name in ("chromium", "chromium-browser"):
        p = shutil.which(name)
        if p:
            return p
    return None


def launch(pw):
    """Debian's Chromium under Playwright (no browser download), with a fresh profile."""
    exe = chromium_path()
    if exe is None:
        pytest.skip("Debian's chromium is not installed (as root: apt-get install chromium; `make test` does it "
                    "where it can)")
    return pw.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS)


@pytest.fixture(scope="module")
def playwright():
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("the Python package playwright is not installed (pip install playwright; it is in the test extras)")
    with sync_playwright() as pw:
        yield pw


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """``mtcw run`` on free ports; yields its URL; stopped with SIGTERM."""
    tmp = tmp_path_factory.mktemp("browser")
    scene = tmp / "browser.toml"
    scene.write_text(SCENE)
    env = {**os.environ, "MTCW_STORE_PATH": ":memory:", "MTCW_VIEW_RATE_HZ": "2"}
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", "--scene", str(scene), "--rate", "10",
                             "--port", "0", "--base-port", "0"], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    url = None
    deadline = time.monotonic() + 120
    try:
        for line in proc.stdout:
            m = re.search(r"live view\s*:\s*(\S+)", line)
            if m:
                url = m.group(1).rstrip("/")
                break
            assert time.monotonic() < deadline, "mtcw run did not print its URL"
        assert url, "mtcw run ended before printing its URL"
        while httpx.get(f"{url}/v1/points/latest").status_code != 200:
            assert time.monotonic() < deadline, "no point from mtcw run"
            time.sleep(0.2)
        yield url
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _wait_js(page, expr: str, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = page.evaluate(expr)
        if got:
            return got
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def test_live_view_in_chromium(playwright, live):
    OUT.mkdir(parents=True, exist_ok=True)
    browser = launch(playwright)
    try:
        page = browser.new_page(viewport={"width": 1440, "height": 900})
        problems: list[str] = []
        page.on("console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type in ("error", "warning")
                else None)
        page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
        page.on("requestfailed", lambda r: problems.append(f"request failed: {r.url}"))
        t0 = time.monotonic()
        page.goto(f"{live}/")
        # live points drawn (not only the history the stream starts with)
        _wait_js(page, "mtcwView.latencies.length >= 3", 15, "live points on the page")
        first_s = time.monotonic() - t0
        _wait_js(page, "mtcwView.diagnostics >= 1 && mtcwView.status !== null", 20, "a spectrum and the counts")
        # the same range as /v1/points/latest: the page's newest point of the source, same seq
        for _ in range(400):  # the page's text follows at 4 Hz, the points at 10/s: look until they meet
            api = httpx.get(f"{live}/v1/points/latest").json()["points"]
            src, p = next(iter(api.items()))
            shown = page.evaluate(f"""(() => {{ const e = document.querySelector('#latest .src[data-source="{src}"]');
                                    return e ? [Number(e.dataset.seq), e.dataset.rangeM, e.textContent] : null; }})()""")
            if shown and shown[0] == p["seq"]:
                break
            time.sleep(0.05)
        assert shown and shown[0] == p["seq"], (shown, p["seq"])
        assert float(shown[1]) == p["targets"][0]["range_m"]
        assert f"{p['targets'][0]['range_m']:.8g}" in shown[2].replace("\u2009", "")
        assert abs(p["targets"][0]["range_m"] - 1.7) < 1e-3  # and it is the truth
        time.sleep(4)  # a few more seconds of updates for the latency figures
        view = page.evaluate("({lat: mtcwView.latencies, points: mtcwView.points, drawn: mtcwView.drawn, "
                             "diag: mtcwView.diagnostics, errors: mtcwView.errors})")
        spectrum_marks = page.evaluate("document.querySelector('#spec-info').textContent")
        page.screenshot(path=str(OUT / "live.png"), full_page=True)
    finally:
        browser.close()
    lat = sorted(view["lat"])
    stats = {"first_live_point_s": round(first_s, 2), "points": view["points"], "redraws": view["drawn"],
             "diagnostics": view["diag"], "trigger_to_pixel_ms": {
                 "n": len(lat), "p50": lat[len(lat) // 2], "p95": lat[int(0.95 * (len(lat) - 1))], "max": lat[-1]}}
    (OUT / "latency.json").write_text(json.dumps(stats, indent=1))
    print("live view:", json.dumps(stats))
    assert not problems, problems
    assert not view["errors"], view["errors"]
    assert "lines used" in spectrum_marks
    assert first_s < 15, "the page must update within seconds"
    assert stats["trigger_to_pixel_ms"]["p50"] < 3000, stats
