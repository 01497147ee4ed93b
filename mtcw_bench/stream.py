"""Sustained frames/s and trigger-to-point latency of the streaming services.

    mtcw-bench-stream [--workers 1 2] [--seconds 20] [--scene cw-bench]

Replays a recording of the scene (1e6-sample frames for cw-bench) through acquisition ->
worker(s) -> API on loopback, each a separate process:
1. throughput: the acquisition publishes as fast as the workers take frames (drop policy
   ``block``); frames/s = points per second at the API over the measuring window;
2. latency: the acquisition publishes at 80 % of that rate (drop policy ``drop``); p50/p99 of
   trigger-to-point latency measured at the API over the window.
Prints a JSON summary and a Markdown table.
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

from services.supervisor import Supervisor


def deploy(recording: Path, workers: int, rate: float, policy: str, profile: str) -> Supervisor:
    """API, acquisition (replay) and workers on loopback; every port bound as 0 and reported, so
    nothing is guessed (the API's URL is ``sup.endpoints["http_url"]`` once started)."""
    env = {"MTCW_FRAMES_ENDPOINT": "tcp://127.0.0.1:0", "MTCW_MONITOR_ENDPOINT": "tcp://127.0.0.1:0",
           "MTCW_POINTS_ENDPOINT": "tcp://127.0.0.1:0", "MTCW_DROP_POLICY": policy, "MTCW_RETENTION_POINTS": "100000",
           "MTCW_STORE_PATH": ":memory:"}  # each measurement starts with an empty history
    sup = Supervisor(env=env)
    sup.add("api", "api", "--port", "0", reports=True)
    sup.add("acq", "acquire", "--source", "replay", "--recording", str(recording), "--loop", "--rate", str(rate),
            reports=True, env={"MTCW_WAIT_FOR_WORKERS": str(workers), "MTCW_WAIT_FOR_WORKER_S": "60"})
    for i in range(workers):
        sup.add(f"w{i}", "worker", "--profile", profile, "--name", f"w{i}")
    return sup


def _wait_up(url: str, timeout: float = 60) -> None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        try:
            if httpx.get(f"{url}/readyz", timeout=1).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    raise RuntimeError("services did not come up")


def measure(recording: Path, workers: int, seconds: float, rate: float, policy: str, profile: str) -> dict:
    sup = deploy(recording, workers, rate, policy, profile)
    sup.start()
    url = sup.endpoints["http_url"]
    try:
        _wait_up(url)
        time.sleep(2.0)  # warm-up: caches, queues filled
        h0 = httpx.get(f"{url}/healthz").json()
        last = httpx.get(f"{url}/v1/points/latest").json()["points"]
        seq0 = max(p["seq"] for p in last.values())
        t0 = time.monotonic()
        time.sleep(seconds)
        h1 = httpx.get(f"{url}/healthz").json()
        dt = time.monotonic() - t0
        pts = httpx.get(f"{url}/v1/points", params={"since_seq": seq0, "limit": 10000}).json()["points"]
    finally:
        sup.stop()
    lat = np.array([p["latency_s"] for p in pts if p.get("latency_s") is not None])
    chain = np.array([sum(p["stage_seconds"].values()) for p in pts if p["status"] == "ok"])
    return {
        "workers": workers, "policy": policy, "rate_hz": rate, "seconds": dt,
        "frames_per_s": (h1["processed"] + h1["rejected"] - h0["processed"] - h0["rejected"]) / dt,
        "dropped": h1["dropped"] - h0["dropped"],
        "latency_p50_s": float(np.percentile(lat, 50)) if lat.size else None,
        "latency_p99_s": float(np.percentile(lat, 99)) if lat.size else None,
        "chain_median_s": float(np.median(chain)) if chain.size else None,
        "points": len(pts),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--scene", default="cw-bench")
    ap.add_argument("--profile", default="balanced")
    ap.add_argument("--out", type=Path, default=Path("out") / "stream")
    args = ap.parse_args()
    rec = args.out / f"{args.scene}"
    if not Path(str(rec) + ".sigmf-meta").exists():
        subprocess.run([sys.executable, "-m", "services.cli", "simulate", args.scene, "-o", str(rec), "-n", "8"],
                       check=True)
    rows = []
    for w in args.workers:
        thr = measure(rec, w, args.seconds, 0.0, "block", args.profile)
        lat = measure(rec, w, args.seconds, 0.8 * thr["frames_per_s"], "drop", args.profile)
        rows.append({"workers": w, "throughput": thr, "latency_at_80pct": lat})
        print(json.dumps(rows[-1], indent=1), file=sys.stderr)
    print(json.dumps(rows, indent=1))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "stream.json").write_text(json.dumps({"command": "mtcw-bench-stream " + " ".join(sys.argv[1:]),
                                                      "rows": rows}, indent=1))
    print(f"\n| workers | frames/s (block) | chain median (ms) | rate for latency (/s) | p50 latency (ms) | "
          f"p99 latency (ms) | dropped |\n|---|---|---|---|---|---|---|")
    for r in rows:
        t, lt = r["throughput"], r["latency_at_80pct"]
        print(f"| {r['workers']} | {t['frames_per_s']:.2f} | {1e3 * (t['chain_median_s'] or 0):.0f} | "
              f"{lt['rate_hz']:.2f} | {1e3 * lt['latency_p50_s']:.0f} | {1e3 * lt['latency_p99_s']:.0f} | "
              f"{lt['dropped']} |")


if __name__ == "__main__":
    main()
