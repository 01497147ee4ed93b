"""Worker throughput with 0 and with N live-view pages open (issue 15: the view never slows the pipeline).

    mtcw-bench-view [--pages 0 5] [--seconds 20] [--repeats 2] [--scene cw-bench]

Replays a recording of the scene (1e6-sample cw-bench frames) through acquisition -> 1 worker ->
API on loopback, as fast as the worker takes frames (drop policy ``block``), and counts the
frames processed per second at the API over the window, first with no page open, then with N
pages of the live view open in headless Chromium (one browser, N tabs, each with its own push
stream with spectra and status). The pages, the browser and the API's feed run on the same
machine as the worker: on a 2-core machine whatever they cost comes out of the worker's share,
which is what this measures. Also reports each page's trigger-to-pixel latency and the feed's
counts. Needs Debian's ``chromium`` and the ``playwright`` package (test extras).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import psutil

from services.supervisor import Supervisor, free_ports

from .stream import _wait_up

CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def deploy(recording: Path, profile: str) -> Supervisor:
    """API, replaying acquisition and one worker; free ports, the monitor's chosen here (the API
    subscribes to it for the view's spectra)."""
    env = {"MTCW_FRAMES_ENDPOINT": "tcp://127.0.0.1:0",
           "MTCW_MONITOR_ENDPOINT": f"tcp://127.0.0.1:{free_ports(1)[0]}",
           "MTCW_POINTS_ENDPOINT": "tcp://127.0.0.1:0", "MTCW_DROP_POLICY": "block", "MTCW_STORE_PATH": ":memory:"}
    sup = Supervisor(env=env)
    sup.add("api", "api", "--port", "0", reports=True)
    sup.add("acq", "acquire", "--source", "replay", "--recording", str(recording), "--loop", "--rate", "0",
            reports=True, env={"MTCW_WAIT_FOR_WORKERS": "1", "MTCW_WAIT_FOR_WORKER_S": "60"})
    sup.add("w0", "worker", "--profile", profile, "--name", "w0")
    return sup


def _cpu_s(procs: dict[str, list[psutil.Process]]) -> dict[str, float]:
    """CPU seconds (user + system) used so far by each group of processes."""
    out = {}
    for name, ps in procs.items():
        total = 0.0
        for p in ps:
            try:
                t = p.cpu_times()
                total += t.user + t.system
            except psutil.Error:
                pass
        out[name] = total
    return out


def measure(recording: Path, pages: int, seconds: float, profile: str, pw) -> dict:
    sup = deploy(recording, profile)
    sup.start()
    url = sup.endpoints["http_url"]
    browser = None
    try:
        _wait_up(url)
        open_pages = []
        if pages:
            browser = pw.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS)
            for _ in range(pages):
                p = browser.new_page(viewport={"width": 1440, "height": 900})
                p.goto(f"{url}/")
                open_pages.append(p)
        time.sleep(3.0)  # warm-up: pages loaded and streaming, queues filled
        kids = {c.name: psutil.Process(c.proc.pid) for c in sup.children}
        procs = {"worker": [kids["w0"]], "api": [kids["api"]], "acquisition": [kids["acq"]],
                 "browser": [p for p in psutil.Process().children(recursive=True) if "chrom" in p.name().lower()]}
        c0 = _cpu_s(procs)
        h0 = httpx.get(f"{url}/healthz").json()
        t0 = time.monotonic()
        time.sleep(seconds)
        h1 = httpx.get(f"{url}/healthz").json()
        dt = time.monotonic() - t0
        c1 = _cpu_s(procs)
        status = httpx.get(f"{url}/v1/view/status").json()
        lat = []
        for p in open_pages:
            lat += p.evaluate("mtcwView.latencies")
    finally:
        if browser is not None:
            browser.close()
        sup.stop()
    lat = np.asarray(lat)
    return {"pages": pages, "seconds": dt,
            "frames_per_s": (h1["processed"] + h1["rejected"] - h0["processed"] - h0["rejected"]) / dt,
            "trigger_to_pixel_p50_ms": float(np.percentile(lat, 50)) if lat.size else None,
            "trigger_to_pixel_p95_ms": float(np.percentile(lat, 95)) if lat.size else None,
            "cpu_cores": {k: round((c1[k] - c0[k]) / dt, 3) for k in c0}, "load_avg_1min": psutil.getloadavg()[0],
            "feed": status["view"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pages", type=int, nargs="+", default=[0, 5])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--repeats", type=int, default=2, help="alternate the page counts this many times")
    ap.add_argument("--scene", default="cw-bench")
    ap.add_argument("--profile", default="balanced")
    ap.add_argument("--out", type=Path, default=Path("out") / "view")
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    rec = args.out / args.scene
    if not Path(str(rec) + ".sigmf-meta").exists():
        subprocess.run([sys.executable, "-m", "services.cli", "simulate", args.scene, "-o", str(rec), "-n", "8"],
                       check=True)
    rows = []
    with sync_playwright() as pw:
        for _ in range(args.repeats):
            for n in args.pages:
                rows.append(measure(rec, n, args.seconds, args.profile, pw))
                print(json.dumps(rows[-1]), file=sys.stderr)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "view.json").write_text(json.dumps({"command": "mtcw-bench-view " + " ".join(sys.argv[1:]),
                                                    "rows": rows}, indent=1))
    print("\n| pages open | worker frames/s | trigger-to-pixel p50 / p95 (ms) | spectra explained / frames passed over "
          "| CPU cores used: worker / API / browser | load (1 min) |\n|---|---|---|---|---|---|")
    for r in rows:
        f = r["feed"] or {}
        lat = "–" if r["trigger_to_pixel_p50_ms"] is None else \
            f"{r['trigger_to_pixel_p50_ms']:.0f} / {r['trigger_to_pixel_p95_ms']:.0f}"
        c = r["cpu_cores"]
        print(f"| {r['pages']} | {r['frames_per_s']:.2f} | {lat} | {f.get('explained', 0)} / {f.get('passed_over', 0)} "
              f"| {c['worker']:.2f} / {c['api']:.2f} / {c['browser']:.2f} | {r['load_avg_1min']:.1f} |")


if __name__ == "__main__":
    main()
