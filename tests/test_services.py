"""The services end to end over real sockets on loopback, with a simulated publisher.

Each service runs as its own process (``python -m services.cli ...``), as in production;
frames are small (2^14 samples) so that the tests are quick on two cores. Nothing guesses a free
port: the API and the acquisition node bind port 0 and report their endpoints
(``MTCW_ENDPOINTS_FILE``), and the processes started after them connect to those. The API's
HTTP behaviour that needs no deployment is tested in-process in ``tests/test_api.py``.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import zmq

from services.acquisition import Publisher
from services.monitor import Subscriber
from services.settings import AcquisitionSettings, TransportSettings
from services.sockets import wait_for_endpoints
from services.supervisor import free_ports

from .conftest import make_scene

ROOT = Path(__file__).resolve().parents[1]
RANGE = 1.234


class Bench:
    """Processes of one test's deployment, every service bound to port 0 and reporting its endpoints."""

    def __init__(self, tmp: Path) -> None:
        self.http = ""
        self.port = 0
        any_port = "tcp://127.0.0.1:0"
        self.env = {**os.environ, "MTCW_FRAMES_ENDPOINT": any_port, "MTCW_MONITOR_ENDPOINT": any_port,
                    "MTCW_POINTS_ENDPOINT": any_port, "MTCW_REORDER_TIMEOUT_S": "1.0", "MTCW_WAIT_FOR_WORKER_S": "60",
                    "PYTHONUNBUFFERED": "1"}
        self.tmp = tmp
        self.procs: dict[str, subprocess.Popen] = {}
        sc = make_scene(digitizer={"samples": 2**14}, noise={"shot": True, "thermal": True},
                        targets=[{"range_m": RANGE, "loss_db": 20.0}])
        self.scene = tmp / "scene.json"
        self.scene.write_text(sc.model_dump_json())

    def start(self, name: str, *args: str, env: dict | None = None, reports: bool = False) -> subprocess.Popen:
        """Start a service; with ``reports``, wait for its bound endpoints and give them to the
        services started after it."""
        log = open(self.tmp / f"{name}.log", "ab")
        report = self.tmp / f"{name}.endpoints.json"
        extra = {"MTCW_ENDPOINTS_FILE": str(report)} if reports else {}
        proc = subprocess.Popen([sys.executable, "-m", "services.cli", *args], cwd=ROOT,
                                env={**self.env, **(env or {}), **extra}, stdout=log, stderr=subprocess.STDOUT)
        self.procs[name] = proc
        if reports:
            got = wait_for_endpoints(report, 60, alive=lambda: proc.poll() is None)
            self.env.update({f"MTCW_{k.upper()}": v for k, v in got.items() if k.endswith("_endpoint")})
            if "http_url" in got:
                self.http = got["http_url"]
                self.port = int(self.http.rsplit(":", 1)[1])
        return proc

    def api(self) -> None:
        self.start("api", "api", "--port", "0", reports=True)
        self.wait(lambda: httpx.get(f"{self.http}/healthz", timeout=1).status_code == 200, "API up")

    def acquire(self, frames: int, rate: float, name: str = "acquisition", workers: int = 1,
                env: dict | None = None) -> subprocess.Popen:
        """Start the acquisition node; it binds (the first time on port 0, later on the endpoints
        the first reported) and waits for ``workers`` workers before its first frame."""
        return self.start(name, "acquire", "--scene", str(self.scene), "--frames", str(frames), "--rate", str(rate),
                          "--seed", "1", env={"MTCW_WAIT_FOR_WORKERS": str(workers), **(env or {})}, reports=True)

    def stop(self, name: str, sig=signal.SIGTERM, timeout: float = 10) -> int:
        proc = self.procs[name]
        if proc.poll() is None:
            proc.send_signal(sig)
        return proc.wait(timeout)

    def get(self, path: str, **params) -> httpx.Response:
        return httpx.get(f"{self.http}{path}", params=params, timeout=5)

    def health(self) -> dict:
        return self.get("/healthz").json()

    @staticmethod
    def wait(cond, what: str, timeout: float = 120.0) -> None:
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            try:
                if cond():
                    return
            except (httpx.HTTPError, ValueError, KeyError):  # not up yet: no answer, or not JSON yet
                pass
            time.sleep(0.1)
        raise AssertionError(f"timed out waiting for {what}")

    def close(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()

    def log(self, name: str) -> str:
        return (self.tmp / f"{name}.log").read_text(errors="replace")

    def all_points(self) -> list[dict]:
        return self.get("/v1/points", limit=10_000).json()["points"]

    def stream_scene(self, scene, frames: int, rate: float, *worker_args: str) -> tuple[dict, list[dict]]:
        """``scene`` through the acquisition node and one ``mtcw worker *worker_args`` to the API: the
        health once every frame is accounted for, and every point served."""
        self.scene.write_text(scene.model_dump_json())
        self.api()
        self.acquire(frames=frames, rate=rate)
        self.start("worker", "worker", *worker_args)
        return _wait_total(self, frames), self.all_points()


@pytest.fixture
def bench(tmp_path):
    b = Bench(tmp_path)
    yield b
    b.close()


def _wait_total(bench: Bench, n: int, timeout: float = 150) -> dict:
    bench.wait(lambda: (lambda h: h["processed"] + h["rejected"] + h["dropped"] >= n and h["held_for_reordering"] == 0)(
        bench.health()), f"{n} frames accounted for", timeout)
    return bench.health()


def test_frames_in_points_out_with_correct_ranges_and_metrics(bench):
    bench.api()
    assert bench.get("/readyz").status_code == 503  # no frame yet
    bench.acquire(frames=20, rate=20)  # publishes once the worker has connected
    bench.start("worker", "worker")
    h = _wait_total(bench, 20)
    assert h["received"] == h["processed"] + h["rejected"]
    assert h["processed"] + h["dropped"] == 20
    assert h["dropped"] == 0
    latest = bench.get("/v1/points/latest").json()["points"]["bench"]
    assert latest["seq"] == 19 and latest["status"] == "ok"
    t = latest["targets"][0]
    assert abs(t["range_m"] - RANGE) < 5 * t["range_sigma_m"] + 1e-5
    assert bench.get("/v1/points/latest", source="bench").json()["seq"] == 19
    assert bench.get("/readyz").status_code == 200
    pts = bench.all_points()
    assert [p["seq"] for p in pts] == list(range(20))
    assert all(abs(p["targets"][0]["range_m"] - RANGE) < 5 * p["targets"][0]["range_sigma_m"] + 1e-5 for p in pts)
    assert [p["seq"] for p in bench.get("/v1/points", since_seq=15, limit=2).json()["points"]] == [16, 17]
    metrics = bench.get("/metrics")
    assert metrics.headers["content-type"].startswith("text/plain")
    text = metrics.text
    for name in ("mtcw_frames_received_total 20.0", "mtcw_frames_processed_total 20.0", "mtcw_frames_dropped_total 0.0",
                 'mtcw_stage_duration_seconds_count{stage="extract"} 20.0', "mtcw_frame_latency_seconds_count 20.0",
                 'mtcw_range_meters{source="bench"}', "mtcw_velocity_meters_per_second", 'mtcw_tone_snr_db{tone="500000000"}',
                 "mtcw_last_frame_age_seconds"):
        assert name in text, name
    assert bench.get("/openapi.json").json()["paths"].keys() >= {"/v1/points/latest", "/v1/points", "/metrics"}


def test_two_workers_every_point_exactly_once_in_order(bench):
    bench.api()
    bench.acquire(frames=60, rate=200, workers=2)  # both workers busy, out-of-order finishes
    bench.start("w0", "worker", "--name", "w0")
    bench.start("w1", "worker", "--name", "w1")
    h = _wait_total(bench, 60)
    seqs = [p["seq"] for p in bench.all_points()]
    assert seqs == sorted(set(seqs))  # in order, no duplicates
    assert len(seqs) + h["dropped"] == 60 and h["rejected"] == 0
    # both took part: each worker logs what it received when it stops
    import re

    got = []
    for w in ("w0", "w1"):
        assert bench.stop(w) == 0
        got.append(int(re.search(r"stopped \(received (\d+)", bench.log(w)).group(1)))
    assert min(got) > 0 and sum(got) == len(seqs)


def test_frames_lost_after_the_last_arrival_are_counted_from_the_end_notice(bench):
    """The tail of a run leaves no seq gap behind it; the end-of-run notice makes it count."""
    from mtcw_core.simulate import simulate_frame

    bench.api()
    st = AcquisitionSettings(frames_endpoint="tcp://127.0.0.1:0", monitor_endpoint="tcp://127.0.0.1:0",
                             drop_policy="block")
    ctx = zmq.Context()
    pub = Publisher(st, ctx)
    try:
        bench.start("worker", "worker", env={"MTCW_FRAMES_ENDPOINT": pub.frames_endpoint})
        assert pub.wait_for_worker(60)
        fr = simulate_frame(make_scene(digitizer={"samples": 2**12}))
        for _ in range(8):
            pub.send(fr)
        pub.seq += 5  # five frames lost on the way (never sent): nothing after them shows a gap
        assert pub.finish(10)
    finally:
        pub.close()
        ctx.term()
    h = _wait_total(bench, 13, timeout=60)
    assert (h["processed"], h["dropped"], h["awaited_after_end"]) == (8, 5, 0)
    assert "mtcw_frames_dropped_total 5.0" in bench.get("/metrics").text


def test_worker_killed_and_restarted_loses_only_what_is_counted(bench):
    bench.api()
    bench.acquire(frames=60, rate=15, workers=2)
    bench.start("w0", "worker", "--name", "w0")
    bench.start("w1", "worker", "--name", "w1")
    bench.wait(lambda: bench.health()["processed"] >= 15, "first points")
    bench.stop("w1", signal.SIGKILL)
    time.sleep(0.5)
    bench.start("w1b", "worker", "--name", "w1b")
    h = _wait_total(bench, 60)
    seqs = [p["seq"] for p in bench.all_points()]
    assert seqs == sorted(set(seqs)), "a point was duplicated or out of order"
    assert len(seqs) + h["dropped"] == 60  # every frame: a point, or counted as dropped
    assert h["received"] == h["processed"] + h["rejected"]
    stale = h["rejected"]  # points that came after their slot was given up (counted, not shown)
    assert stale <= 5


def test_publisher_restart_workers_reconnect_and_old_frames_are_not_new(bench):
    bench.api()
    bench.acquire(frames=10, rate=20, name="acq1")
    bench.start("worker", "worker")
    assert bench.procs["acq1"].wait(30) == 0
    _wait_total(bench, 10)
    first = bench.get("/v1/points/latest").json()["points"]["bench"]
    bench.acquire(frames=10, rate=20, name="acq2")  # same endpoints, new process: seq starts at 0 again
    bench.wait(lambda: bench.get("/v1/points/latest").json()["points"]["bench"]["t_ns"] > first["t_ns"]
               and bench.get("/v1/points/latest").json()["points"]["bench"]["seq"] == 9, "second run's points")
    pts = bench.all_points()
    t = [p["t_ns"] for p in pts]
    assert [p["seq"] for p in pts] == list(range(10)) * 2
    assert t == sorted(t)  # the new run's points are newer than all of the old run's


def test_slow_subscriber_overflow_is_counted_as_dropped():
    """A monitor that does not keep up loses frames at its high-water mark, and knows how many."""
    st = AcquisitionSettings(frames_endpoint="tcp://127.0.0.1:0", monitor_endpoint="tcp://127.0.0.1:0", hwm=4)
    ctx = zmq.Context()
    pub = Publisher(st, ctx)
    sub = Subscriber(TransportSettings(monitor_endpoint=pub.monitor_endpoint, hwm=2), ctx, rcvhwm=2)
    from mtcw_core.simulate import simulate_frame

    fr = simulate_frame(make_scene(digitizer={"samples": 2**12}))
    stop = threading.Event()
    it = sub.frames(stop, timeout_ms=50)
    # wait until the subscription is live, then flood without reading
    got = []
    for _ in range(100):
        pub.send(fr)
        sub_ready = sub.sock.poll(50)
        if sub_ready:
            got.append(next(it))
            break
    n_pub0 = pub.seq
    for _ in range(200):
        pub.send(fr)
    time.sleep(0.3)
    pub.send(fr)  # a last frame after the backlog, so the gap before it is visible
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
        if not sub.sock.poll(300):
            break
        got.append(next(it))
    stop.set()
    seqs = [f.seq for f in got]
    assert seqs[-1] == pub.seq - 1
    assert sub.gaps.dropped > 100  # the PUB queue overflowed
    assert sub.gaps.received + sub.gaps.dropped == seqs[-1] - seqs[0] + 1  # nothing lost silently
    assert pub.dropped == pub.seq  # no worker connected: every frame counted as dropped on the PUSH side
    assert n_pub0 >= 1
    sub.close()
    pub.close()
    ctx.term()


def test_mtcw_record_writes_the_monitor_stream_to_sigmf(bench):
    from mtcw_core.recording import read_recording

    out = bench.tmp / "cap"
    # no worker: the node publishes at once (frames to workers dropped and counted); the recorder
    # subscribes to the monitor endpoint it reported and takes 5 of them
    bench.acquire(frames=2000, rate=50, env={"MTCW_WAIT_FOR_WORKER_S": "0"})
    rec = bench.start("record", "record", "-o", str(out), "-n", "5")
    assert rec.wait(60) == 0, bench.log("record")
    r = read_recording(out)
    assert len(r) == 5
    assert r.frame(0).truth[0].range_m == pytest.approx(RANGE)
    assert json.loads(bench.log("record").strip().splitlines()[-1])["frames"] == 5


def test_mtcw_run_serves_points_and_stops_cleanly_on_sigterm(tmp_path):
    import re

    p = [0, 0]  # HTTP port and --base-port 0: every service binds a free port and reports it
    scene = Bench(tmp_path).scene
    log = open(tmp_path / "run.log", "wb")
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", "--scene", str(scene),
                             "--port", str(p[0]), "--base-port", str(p[1]), "--rate", "10", "--track", "3"],
                            cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        found = {}

        def announced() -> bool:
            m = re.search(r"latest point : curl (http://\S+/v1/points/latest)", (tmp_path / "run.log").read_text())
            found["url"] = m and m.group(1)
            return bool(m)

        Bench.wait(announced, "mtcw run to print its URLs", 60)
        url = found["url"]
        Bench.wait(lambda: httpx.get(url, timeout=1).status_code == 200, "a point from mtcw run", 60)
        t = httpx.get(url).json()["points"]["bench"]["targets"][0]
        assert abs(t["range_m"] - RANGE) < 5 * t["range_sigma_m"] + 1e-5
        # --track 3: from the third frame on, the (static) target's range rate through wire and API
        Bench.wait(lambda: httpx.get(url).json()["points"]["bench"]["targets"][0]["track_frames"] >= 3,
                   "a tracked point", 30)
        t = httpx.get(url).json()["points"]["bench"]["targets"][0]
        assert t["track_id"] >= 1 and abs(t["range_rate_mps"]) < 5 * t["range_rate_sigma_mps"]
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0
        out = (tmp_path / "run.log").read_text()
        assert "stopped (SIGTERM)" in out
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    # no child left behind
    time.sleep(0.5)
    ps = subprocess.run(["pgrep", "-f", f"--port {p[0]}"], capture_output=True, text=True).stdout.strip()
    assert ps == ""
    # (the pattern above starts with "--", which pgrep takes for an option: it matches nothing)
    left = subprocess.run(["pgrep", "-f", "--", str(scene)], capture_output=True, text=True)
    assert left.returncode == 1 and left.stdout.strip() == "", left.stdout  # 1: no process matched


def test_a_service_asked_for_its_stacks_writes_them_and_still_stops_cleanly(bench):
    """SIGUSR1 (what the supervisor and the soak send a service that will not stop) writes every
    thread's stack to the log; the service goes on, and SIGTERM still stops it with status 0."""
    proc = bench.acquire(frames=5, rate=10.0)  # waits for a worker that never comes
    proc.send_signal(signal.SIGUSR1)
    # faulthandler's frame lines read 'File "...acquisition.py", line N in wait_for_worker' (the
    # settings logged at start name "wait_for_worker_s" too: not that)
    Bench.wait(lambda: re.search(r'acquisition\.py", line \d+ in wait_for_worker\n', bench.log("acquisition")),
               "the stacks in the log", 10)
    assert "Current thread" in bench.log("acquisition")
    assert proc.poll() is None
    assert bench.stop("acquisition") == 0


def test_supervisor_asks_a_child_that_will_not_stop_for_its_stacks(tmp_path):
    from services.supervisor import Supervisor

    sup = Supervisor(env={}, stop_timeout_s=1.0)
    sup.add("stuck", "acquire")
    log = open(tmp_path / "stuck.log", "wb")
    # a child that ignores SIGTERM but dumps its stacks on SIGUSR1, as a hung service would
    code = ("import faulthandler, signal, sys, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
            "faulthandler.register(signal.SIGUSR1, all_threads=True); print('up', flush=True); time.sleep(60)")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=log, stderr=subprocess.STDOUT)
    sup.children[0].proc = proc
    Bench.wait(lambda: "up" in (tmp_path / "stuck.log").read_text(), "the child up", 20)
    codes = sup.stop()
    assert codes["stuck"] == -signal.SIGKILL
    assert 'File "<string>", line 1 in <module>' in (tmp_path / "stuck.log").read_text()


def test_bad_settings_name_the_field(tmp_path):
    r = subprocess.run([sys.executable, "-m", "services.cli", "worker", "--profile", "turbo"], cwd=ROOT,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode != 0 and "profile" in r.stderr and "turbo" in r.stderr
    r = subprocess.run([sys.executable, "-m", "services.cli", "acquire"], cwd=ROOT, capture_output=True, text=True,
                       timeout=60, env={**os.environ, "MTCW_FRAMES_ENDPOINT": "localhost:5555"})
    assert r.returncode != 0 and "frames_endpoint" in r.stderr


@pytest.mark.skipif(shutil.which("prometheus") is None,
                    reason="Debian package 'prometheus' not installed (make test installs it where it can)")
def test_a_real_prometheus_scrapes_metrics(bench):
    bench.api()
    prom_port = free_ports(1)[0]
    cfg = bench.tmp / "prometheus.yml"
    cfg.write_text(f"""global:\n  scrape_interval: 1s\nscrape_configs:\n  - job_name: mtcw\n    static_configs:\n"""
                   f"""      - targets: ['127.0.0.1:{bench.port}']\n""")
    proc = subprocess.Popen(["prometheus", f"--config.file={cfg}", f"--storage.tsdb.path={bench.tmp / 'tsdb'}",
                             f"--web.listen-address=127.0.0.1:{prom_port}"], stdout=subprocess.DEVNULL,
                            stderr=open(bench.tmp / "prometheus.log", "wb"))
    bench.procs["prometheus"] = proc
    q = f"http://127.0.0.1:{prom_port}/api/v1/query"

    def scraped() -> bool:
        r = httpx.get(q, params={"query": 'up{job="mtcw"}'}, timeout=2).json()
        return bool(r["data"]["result"]) and r["data"]["result"][0]["value"][1] == "1"

    bench.wait(scraped, "Prometheus to scrape /metrics", 60)
    r = httpx.get(q, params={"query": "mtcw_frames_received_total"}, timeout=2).json()
    assert r["status"] == "success" and r["data"]["result"]
    targets = httpx.get(f"http://127.0.0.1:{prom_port}/api/v1/targets", timeout=2).json()["data"]["activeTargets"]
    assert targets[0]["health"] == "up" and targets[0]["lastError"] == ""
    assert np.isfinite(float(r["data"]["result"][0]["value"][1]))
