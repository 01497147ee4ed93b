"""docker-compose.yml, Prometheus and Grafana files: they parse, and every command they run starts.

No container engine runs here, so the compose services' commands are run as plain processes
with the compose environment, endpoints moved to free loopback ports; their healthchecks are
run against them.
"""

from __future__ import annotations

import http.server
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
import pytest
import yaml

from .test_services import ROOT, Bench, free_ports

COMPOSE = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
MTCW_SERVICES = ("acquisition", "worker", "api")


def test_compose_declares_the_services_and_python_healthchecks():
    svc = COMPOSE["services"]
    assert set(svc) == {"keys", "acquisition", "worker", "api", "prometheus", "grafana"}
    for name in MTCW_SERVICES:  # the compose network is not loopback: CurveZMQ everywhere
        assert svc[name]["environment"]["MTCW_CURVE_DIR"] == "/keys" and "mtcw-keys:/keys" in svc[name]["volumes"]
        assert svc[name]["depends_on"]["keys"] == {"condition": "service_completed_successfully"}
    for name in MTCW_SERVICES:
        hc = svc[name]["healthcheck"]["test"]
        assert hc[:3] == ["CMD", "python", "-c"], f"{name}: healthcheck must use python, not curl"
        compile(hc[3], f"{name}-healthcheck", "exec")
        assert svc[name]["build"] == "." and svc[name]["image"] == "mtcw:latest"
    assert "deploy" not in svc["worker"] or "replicas" in svc["worker"]["deploy"]
    assert all(p.startswith("127.0.0.1:") for s in svc.values() for p in s.get("ports", []))
    for vol in svc["prometheus"]["volumes"] + svc["grafana"]["volumes"]:
        assert (ROOT / vol.split(":")[0]).exists(), vol


def test_compose_api_keeps_its_store_in_a_volume_and_checks_health_not_just_liveness():
    api = COMPOSE["services"]["api"]
    store = api["environment"]["MTCW_STORE_PATH"]
    mounts = dict(v.split(":")[::-1] for v in api["volumes"])  # mount point -> volume
    assert store.startswith("/data/") and mounts["/data"] in COMPOSE["volumes"], "the store must outlive the container"
    assert mounts["/keys"] == "mtcw-keys"
    acq = COMPOSE["services"]["acquisition"]  # the run ledger outlives a killed container too
    acq_mounts = dict(v.split(":")[::-1] for v in acq["volumes"])
    assert acq["environment"]["MTCW_STATE_FILE"].startswith("/data/") and acq_mounts["/data"] in COMPOSE["volumes"]
    assert acq_mounts["/data"] != mounts["/data"]
    # the image runs as nobody: /data must be made and handed to it before USER nobody
    dockerfile = (ROOT / "Dockerfile").read_text()
    made = re.search(r"^RUN .*mkdir [^&]*/data.*chown nobody [^&]*/data", dockerfile, re.M)
    assert made and dockerfile.index(made.group(0)) < dockerfile.index("USER nobody")
    hc = api["healthcheck"]["test"][3]
    assert "/healthz" not in hc and ("/readyz" in hc or "/livez" in hc)


class _FakeApi(http.server.BaseHTTPRequestHandler):
    """Answers /readyz?verbose with the checks it is given (status 503 when one fails)."""

    checks: dict = {}

    def do_GET(self):  # noqa: N802 (http.server's name)
        body = json.dumps({"checks": self.checks}).encode()
        self.send_response(200 if all(c["ok"] for c in self.checks.values()) else 503)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


def test_api_healthcheck_fails_on_a_dead_receiver_or_store_not_on_a_quiet_source(tmp_path):
    srv = http.server.HTTPServer(("127.0.0.1", 0), _FakeApi)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    code = _localise(COMPOSE["services"]["api"]["healthcheck"]["test"][3], {8000: srv.server_port}, tmp_path)

    def check(receiver: bool, store: bool, frames: bool) -> int:
        _FakeApi.checks = {"receiver": {"ok": receiver, "why": ""}, "store": {"ok": store, "why": ""},
                           "frames": {"ok": frames, "why": ""}}
        return subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=30).returncode

    try:
        assert check(True, True, True) == 0
        assert check(True, True, False) == 0  # no frame lately: the API itself is fine
        assert check(True, False, True) != 0
        assert check(False, True, True) != 0
    finally:
        srv.shutdown()
        srv.server_close()
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=30).returncode != 0  # no API


def _metric_names() -> set[str]:
    from services.api import Metrics

    names = {m.name for m in Metrics().registry.collect()}
    src = (ROOT / "services" / "acquisition.py").read_text() + (ROOT / "services" / "worker.py").read_text()
    names |= set(re.findall(r'Counter\("(mtcw_\w+?)(?:_total)?"', src))
    return names


def test_grafana_dashboard_queries_metrics_that_exist():
    dash = json.loads((ROOT / "deploy/grafana/dashboards/mtcw.json").read_text())
    titles = {p["title"] for p in dash["panels"]}
    assert {"Range", "Speed", "Frame rate", "Drops"} <= titles and any("latency" in t.lower() for t in titles)
    names = _metric_names()
    for p in dash["panels"]:
        for t in p["targets"]:
            for m in re.findall(r"mtcw_[a-z_]+", t["expr"]):
                base = re.sub(r"_(bucket|total|sum|count)$", "", m)
                assert base in names or m in names, f"{p['title']}: {m} is not exported"
    ds = yaml.safe_load((ROOT / "deploy/grafana/provisioning/datasources/prometheus.yml").read_text())
    assert ds["datasources"][0]["url"] == "http://prometheus:9090"


@pytest.mark.skipif(shutil.which("promtool") is None, reason="promtool (Debian package prometheus) not installed")
def test_prometheus_config_is_valid():
    r = subprocess.run(["promtool", "check", "config", str(ROOT / "deploy/prometheus.yml")], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr


def _localise(text: str, ports: dict[int, int], keys: Path) -> str:
    """A compose string for this machine: loopback, the free ports, the keys in ``keys`` and the
    volume ``/data`` in ``keys``'s parent."""
    text = text.replace("tcp://*:", "tcp://127.0.0.1:").replace("0.0.0.0", "127.0.0.1")
    text = re.sub(r"^/keys$", str(keys), text)
    text = re.sub(r"^/data/", f"{keys.parent / 'data'}/", text)
    text = re.sub(r"tcp://(acquisition|api):", "tcp://127.0.0.1:", text)
    for old, new in ports.items():
        text = re.sub(rf"\b{old}\b", str(new), text)
    return text


def test_every_compose_command_starts_and_passes_its_healthcheck(tmp_path):
    fixed = [5555, 5556, 5557, 9101, 9102, 8000]
    ports = dict(zip(fixed, free_ports(len(fixed))))
    procs: dict[str, subprocess.Popen] = {}
    keys = tmp_path / "keys"
    made = subprocess.run([sys.executable, "-m", "services.cli", *[_localise(a, ports, keys) for a in
                                                                  COMPOSE["services"]["keys"]["command"]]],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert made.returncode == 0 and (keys / "server.key_secret").exists(), made.stderr
    try:
        for name in ("api", "worker", "acquisition"):
            s = COMPOSE["services"][name]
            env = {**os.environ, **{k: _localise(str(v), ports, keys) for k, v in s["environment"].items()}}
            argv = [_localise(a, ports, keys) for a in s["command"]]
            procs[name] = subprocess.Popen([sys.executable, "-m", "services.cli", *argv], cwd=ROOT, env=env,
                                           stdout=open(tmp_path / f"{name}.log", "wb"), stderr=subprocess.STDOUT)
        url = f"http://127.0.0.1:{ports[8000]}/v1/points/latest"
        Bench.wait(lambda: httpx.get(url, timeout=1).status_code == 200, "a point through the compose commands", 90)
        for name in MTCW_SERVICES:
            code = _localise(COMPOSE["services"][name]["healthcheck"]["test"][3], ports, keys)
            r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30)
            assert r.returncode == 0, f"{name} healthcheck: {r.stderr}"
            assert procs[name].poll() is None, f"{name} died"
        store = Path(_localise(COMPOSE["services"]["api"]["environment"]["MTCW_STORE_PATH"], ports, keys))
        assert store.parent == tmp_path / "data" and store.exists()  # the API keeps its history where compose says
    finally:
        for name, p in procs.items():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for name, p in procs.items():
            try:
                code = p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()
                raise AssertionError(f"{name} did not stop on SIGTERM")
            # uvicorn re-raises the signal after its graceful shutdown
            assert code in (0, -signal.SIGTERM), f"{name} exit {code}: {(tmp_path / f'{name}.log').read_text()[-2000:]}"
    time.sleep(0.1)
