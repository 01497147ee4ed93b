"""Soak and fault run of the streaming services: overload, SIGKILLs, and books that must balance.

    mtcw-bench-soak [--seconds 600] [--kills 30] [--workers 2] [--overload 2] [--seed 1] [--out out/soak]

Replays a small recording through acquisition -> worker(s) -> API on loopback, each its own
process, at ``--overload`` times the workers' measured capacity (drop policy ``drop``), and
SIGKILLs a worker, the API or the acquisition node at random moments (``--kills`` in all, each
kind at least once when there are three or more), restarting each victim at once on the same
endpoints, as a container runtime would. At the end the acquisition node is stopped cleanly and
the books are read:

- ``published``: frames the acquisition node stamped, summed over its runs (each run's count
  from its state file, ``MTCW_STATE_FILE``, which the node keeps current before every send);
- the API's ``processed + rejected + dropped`` must equal it exactly, and
  ``received = processed + rejected``;
- no ``(source, run, seq)`` twice in the served history, and within a run the history's seqs
  strictly increase (no stale point served as new);
- the API's resident memory stays bounded (its peak in the second half of the run against the
  first half);
- recovery time of each kill: from the kill until the API has counted a frame more than before it
  (p50 and p99 reported).

Prints and writes ``soak.json``; the exit status is 1 when a check fails.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import httpx
import numpy as np

from services.supervisor import Child, Supervisor, dump_stacks

from .stream import measure

KINDS = ("worker", "api", "acquisition")


@dataclass
class SoakResult:
    """What one soak run measured, and whether each check passed."""

    seconds: float
    capacity_fps: float
    rate_hz: float
    kills: list[dict] = field(default_factory=list)
    published: int = 0
    runs: list[dict] = field(default_factory=list)
    counts: dict = field(default_factory=dict)
    duplicates: int = 0
    stale_served: int = 0
    history_points: int = 0
    api_rss_mb: dict = field(default_factory=dict)
    checks: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return all(self.checks.values())

    def summary(self) -> dict:
        rec = np.array([k["recovery_s"] for k in self.kills if k["recovery_s"] is not None])
        return {
            "ok": self.ok, "checks": self.checks, "seconds": round(self.seconds, 1),
            "capacity_fps": round(self.capacity_fps, 1), "rate_hz": round(self.rate_hz, 1),
            "published": self.published, "counts": self.counts, "runs": self.runs,
            "kills": dict(Counter(k["victim"] for k in self.kills)), "kills_total": len(self.kills),
            "recovery_p50_s": float(np.percentile(rec, 50)) if rec.size else None,
            "recovery_p99_s": float(np.percentile(rec, 99)) if rec.size else None,
            "recovery_max_s": float(rec.max()) if rec.size else None,
            "unrecovered_kills": int(sum(k["recovery_s"] is None for k in self.kills)),
            "duplicates": self.duplicates, "stale_served": self.stale_served,
            "history_points": self.history_points, "api_rss_mb": self.api_rss_mb,
        }


class Stack:
    """API, acquisition node (replay) and workers as child processes that can be killed and restarted."""

    def __init__(self, recording: Path, workers: int, rate_hz: float, profile: str, workdir: Path,
                 reorder_timeout_s: float) -> None:
        self.workdir = workdir
        self.state_file = workdir / "acquisition-state.json"
        env = {"MTCW_FRAMES_ENDPOINT": "tcp://127.0.0.1:0", "MTCW_MONITOR_ENDPOINT": "tcp://127.0.0.1:0",
               "MTCW_POINTS_ENDPOINT": "tcp://127.0.0.1:0", "MTCW_DROP_POLICY": "drop",
               "MTCW_STORE_PATH": str(workdir / "api.sqlite3"), "MTCW_RETENTION_POINTS": "1000000",
               "MTCW_REORDER_TIMEOUT_S": str(reorder_timeout_s), "MTCW_STATE_FILE": str(self.state_file)}
        self.sup = Supervisor(env=env, stop_timeout_s=20.0)
        self.sup.add("api", "api", "--port", "0", reports=True)
        self.sup.add("acquisition", "acquire", "--source", "replay", "--recording", str(recording), "--loop",
                     "--rate", f"{rate_hz:.3f}", reports=True,
                     env={"MTCW_WAIT_FOR_WORKERS": str(workers), "MTCW_WAIT_FOR_WORKER_S": "60"})
        for i in range(workers):
            self.sup.add(f"worker-{i}", "worker", "--profile", profile, "--name", f"worker-{i}")
        self.logs: dict[str, object] = {}

    def start(self) -> None:
        self.sup.start()
        self.url = self.sup.endpoints["http_url"]

    def child(self, name: str) -> Child:
        return next(c for c in self.sup.children if c.name == name)

    def names(self, kind: str) -> list[str]:
        return [c.name for c in self.sup.children if c.name.startswith(kind)]

    def restart(self, name: str) -> None:
        """Start ``name`` again on the endpoints (and HTTP port) the first start reported."""
        c = self.child(name)
        ends = {f"MTCW_{k.upper()}": v for k, v in self.sup.endpoints.items() if k.endswith("_endpoint")}
        argv = list(c.argv)
        if name == "api":
            argv[argv.index("--port") + 1] = self.url.rsplit(":", 1)[1]
        c.proc = subprocess.Popen(argv, env={**os.environ, **self.sup.env, **ends, **c.env,
                                             "MTCW_WAIT_FOR_WORKER_S": "0"})

    def kill(self, name: str) -> None:
        c = self.child(name)
        c.proc.send_signal(signal.SIGKILL)
        c.proc.wait(30)

    def health(self, timeout: float = 1.0) -> Optional[dict]:
        try:
            r = httpx.get(f"{self.url}/healthz", timeout=timeout)
            return r.json() if r.status_code in (200, 503) else None
        except (httpx.HTTPError, ValueError):
            return None

    def api_pid(self) -> Optional[int]:
        p = self.child("api").proc
        return p.pid if p is not None and p.poll() is None else None


def _ledger_runs(path: Path, runs: dict[int, dict]) -> None:
    """Add what the acquisition node's run ledger holds (every run in it, the ended one too) to
    ``runs`` (run id -> its record with the largest frame count)."""
    from services.acquisition import RunLedger

    for rec in RunLedger.read(path, include_ended=True):
        old = runs.get(rec["run"])
        if old is None or rec["frames"] > old["frames"]:
            runs[rec["run"]] = rec


def _history(url: str) -> list[dict]:
    """Every point the API serves, oldest first (paged by the history's cursor)."""
    out: list[dict] = []
    cursor = None
    while True:
        params = {"limit": 10_000, **({"after": cursor} if cursor is not None else {})}
        body = httpx.get(f"{url}/v1/points", params=params, timeout=30).json()
        out += body["points"]
        cursor = body.get("next")
        if not body.get("more") or cursor is None:
            return out


def soak(recording: Path, seconds: float, kills: int, workers: int = 2, overload: float = 2.0, seed: int = 1,
         profile: str = "fast", capacity_fps: Optional[float] = None, reorder_timeout_s: float = 1.0,
         progress=print) -> SoakResult:
    """One soak run (see the module docstring); returns what it measured and the checks."""
    import psutil

    rng = random.Random(seed)
    cap = capacity_fps or measure(recording, workers, 4.0, 0.0, "block", profile)["frames_per_s"]
    res = SoakResult(seconds=seconds, capacity_fps=cap, rate_hz=overload * cap)
    workdir = Path(tempfile.mkdtemp(prefix="mtcw-soak-"))
    stack = Stack(recording, workers, res.rate_hz, profile, workdir, reorder_timeout_s)
    victims = [KINDS[i % 3] for i in range(kills)] if kills >= 3 else [rng.choice(KINDS) for _ in range(kills)]
    rng.shuffle(victims)
    slot = seconds / (kills + 1)
    t_kill = [slot * (i + 1) + rng.uniform(-0.3, 0.3) * slot for i in range(kills)]
    rss: list[tuple[float, float]] = []
    runs: dict[int, dict] = {}  # the acquisition node's runs: id -> ledger record (frames stamped)
    stack.start()
    t0 = time.monotonic()
    try:
        while not (stack.health() or {}).get("processed"):
            if time.monotonic() - t0 > 60:
                raise RuntimeError("no frame processed within 60 s")
            time.sleep(0.2)
        t0 = time.monotonic()
        pending = list(zip(t_kill, victims))
        while (now := time.monotonic() - t0) < seconds:
            pid = stack.api_pid()
            if pid:
                try:
                    rss.append((now, psutil.Process(pid).memory_info().rss / 2**20))
                except psutil.Error:
                    pass
            if pending and now >= pending[0][0]:
                _, kind = pending.pop(0)
                name = rng.choice(stack.names(kind))
                before = stack.health()
                base = (before or {}).get("processed", 0) + (before or {}).get("rejected", 0)
                t_k = time.monotonic()
                stack.kill(name)
                if kind == "acquisition":
                    _ledger_runs(stack.state_file, runs)
                stack.restart(name)
                rec = None
                while time.monotonic() - t_k < 30:
                    h = stack.health(0.5)
                    if h is not None and h["processed"] + h["rejected"] > base:
                        rec = time.monotonic() - t_k
                        break
                    time.sleep(0.02)
                res.kills.append({"victim": kind, "name": name, "at_s": round(t_k - t0, 2), "recovery_s": rec})
                progress(f"soak: killed {name} at {t_k - t0:.1f} s; recovered in "
                         f"{'%.2f s' % rec if rec is not None else 'NOT within 30 s'}")
            time.sleep(0.1)
        # a clean stop of the acquisition node: its end-of-run notice closes the books
        acq = stack.child("acquisition").proc
        acq.send_signal(signal.SIGTERM)
        try:
            res.checks["acquisition_clean_stop"] = acq.wait(30) == 0
        except subprocess.TimeoutExpired:  # a stop that hangs is a failed check, and the soak's books still close
            progress("soak: the acquisition node did not stop within 30 s of SIGTERM; its stacks (stderr), then killed")
            res.checks["acquisition_clean_stop"] = False
            dump_stacks(acq)
            acq.kill()
            acq.wait(10)
        _ledger_runs(stack.state_file, runs)
        res.runs = list(runs.values())
        res.published = sum(int(r["frames"]) for r in res.runs)
        deadline = time.monotonic() + 10 * reorder_timeout_s + 10
        while time.monotonic() < deadline:
            h = stack.health()
            if h and h["held_for_reordering"] == 0 and h["awaited_after_end"] == 0 and \
                    h["processed"] + h["rejected"] + h["dropped"] >= res.published:
                break
            time.sleep(0.2)
        time.sleep(2 * reorder_timeout_s)
        h = stack.health() or {}
        res.counts = {k: h.get(k) for k in ("received", "processed", "rejected", "dropped")}
        hist = _history(stack.url)
    finally:
        codes = stack.sup.stop()
    res.history_points = len(hist)
    keys = Counter((p["source"], p.get("run"), p["seq"]) for p in hist)
    res.duplicates = sum(n - 1 for n in keys.values() if n > 1)
    last: dict = {}
    for p in hist:
        k = (p["source"], p.get("run"))
        if k in last and p["seq"] <= last[k]:
            res.stale_served += 1
        last[k] = max(p["seq"], last.get(k, -1))
    if rss:
        t = np.array([r[0] for r in rss])
        m = np.array([r[1] for r in rss])
        first, second = m[t < seconds / 2], m[t >= seconds / 2]
        res.api_rss_mb = {"peak": float(m.max()), "peak_first_half": float(first.max()) if first.size else None,
                          "peak_second_half": float(second.max()) if second.size else None}
        res.checks["memory_bounded"] = bool(not first.size or not second.size
                                            or second.max() <= 1.25 * first.max() + 50)
    c = res.counts
    res.checks["books_exact"] = c.get("processed", 0) + c.get("rejected", 0) + c.get("dropped", 0) == res.published
    res.checks["received_balances"] = c.get("received") == c.get("processed", 0) + c.get("rejected", 0)
    res.checks["no_duplicates"] = res.duplicates == 0
    res.checks["no_stale_served"] = res.stale_served == 0
    res.checks["every_kill_recovered"] = all(k["recovery_s"] is not None for k in res.kills)
    res.checks["clean_final_stop"] = all(code in (0, -signal.SIGTERM) for name, code in codes.items()
                                         if name != "acquisition")
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=600.0)
    ap.add_argument("--kills", type=int, default=30)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--overload", type=float, default=2.0, help="publish at this multiple of the measured capacity")
    ap.add_argument("--profile", default="fast")
    ap.add_argument("--scene", default="cw-bench")
    ap.add_argument("--samples", type=int, default=2**16)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("out") / "soak")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rec = args.out / f"{args.scene}-{args.samples}"
    if not Path(str(rec) + ".sigmf-meta").exists():
        subprocess.run([sys.executable, "-m", "services.cli", "simulate", args.scene, "-o", str(rec), "-n", "8",
                        "--samples", str(args.samples)], check=True)
    res = soak(rec, args.seconds, args.kills, args.workers, args.overload, args.seed, args.profile,
               progress=lambda s: print(s, file=sys.stderr))
    out = {"command": "mtcw-bench-soak " + " ".join(sys.argv[1:]), **res.summary(), "kill_log": res.kills}
    (args.out / "soak.json").write_text(json.dumps(out, indent=1))
    print(json.dumps(res.summary(), indent=1))
    sys.exit(0 if res.ok else 1)


if __name__ == "__main__":
    main()
