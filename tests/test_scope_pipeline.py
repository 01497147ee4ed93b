"""The scope path end to end: a simulated MDO3 -> ``mtcw acquire --source scope-sim`` -> a worker
-> the API's ``/v1/points/latest``, the range checked against the scene's truth; and the
acquisition node under scope faults (in process, with its Prometheus exporter): failures
counted by reason in ``mtcw_acquisition_errors_total``, no bad frame published, seq and run
going on as if nothing happened.
"""

from __future__ import annotations

import threading
import time

import httpx
import numpy as np
import pytest
import zmq

from services import acquisition
from services.acquisition import run_acquisition
from services.settings import AcquisitionSettings, load
from services.supervisor import free_ports
from services.wire import FRAME_TOPIC, decode_frame

from .conftest import make_scene
from .test_services import RANGE, Bench


@pytest.fixture
def bench(tmp_path):
    b = Bench(tmp_path)
    yield b
    b.close()


def test_simulated_scope_to_latest_point_ranges_at_the_scenes_truth(bench):
    bench.api()
    # Bench's scene: a static target at RANGE, shot and thermal noise, 2^14 samples; the scope
    # records 10^4 points of it at 5 GS/s through an 8-bit ADC, 2 bytes per point
    bench.start("acquisition", "acquire", "--source", "scope-sim", "--scene", str(bench.scene), "--seed", "1",
                "--frames", "8", "--rate", "20", "--record-length", "10000", "--data-width", "2",
                env={"MTCW_VISA_TIMEOUT_S": "10"}, reports=True)
    bench.start("worker", "worker")
    bench.wait(lambda: (lambda h: h["processed"] + h["rejected"] + h["dropped"] >= 8)(bench.health()),
               "8 frames accounted for", 150)
    h = bench.health()
    assert h["processed"] == 8 and h["dropped"] == 0 and h["rejected"] == 0
    latest = bench.get("/v1/points/latest").json()["points"]["bench"]
    assert latest["seq"] == 7 and latest["status"] == "ok"
    pts = bench.all_points()
    assert [p["seq"] for p in pts] == list(range(8))
    for p in pts:
        t = p["targets"][0]
        # the truth of the scene, within 5 of the reported sigmas (an 8-bit scope adds its quantization)
        assert abs(t["range_m"] - RANGE) < 5 * t["range_sigma_m"] + 1e-5, t
        assert t["range_sigma_m"] < 1e-3
    log = bench.log("acquisition")
    assert "scope: settings in force" in log and "TEKTRONIX,MDO34" in log and '"source":"scope-sim"' in log


def test_acquire_refuses_incomplete_scope_settings_naming_the_field(bench):
    import subprocess
    import sys

    from .test_services import ROOT

    out = subprocess.run([sys.executable, "-m", "services.cli", "acquire", "--source", "scope", "--resource",
                          "TCPIP::192.0.2.1::INSTR", "--wavelength-m", "1.064e-6"], cwd=ROOT, env=bench.env,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "tones_hz: source scope needs the bench's tone plan" in out.stderr


def test_node_under_scope_faults_counts_them_and_publishes_only_whole_frames(tmp_path, monkeypatch):
    sc = make_scene(digitizer={"samples": 2**14}, noise={"shot": True, "thermal": True})
    scene = tmp_path / "scene.json"
    scene.write_text(sc.model_dump_json())
    port, frames_port = free_ports(2)
    st = load(AcquisitionSettings, source="scope-sim", scene=str(scene), seed=2, record_length=10_000,
              frames_endpoint=f"tcp://127.0.0.1:{frames_port}", monitor_endpoint="tcp://127.0.0.1:0",
              wait_for_worker_s=60,
              metrics_port=port, visa_timeout_s=0.5, retry_backoff_s=0.01, retry_backoff_max_s=0.05, frames=12,
              drop_policy="block", end_timeout_s=2)
    made = []
    real = acquisition.make_source
    monkeypatch.setattr(acquisition, "make_source", lambda *a, **k: made.append(real(*a, **k)) or made[-1])
    faults = iter(["garbled", "timeout", "gone", "short_block", "record_length", "sample_rate", "unlocked",
                   "truncated", "missed"])
    ctx = zmq.Context()
    pull = ctx.socket(zmq.PULL)
    pull.connect(st.frames_endpoint)  # the node waits for it (a worker) before its first frame
    got: list = []

    def on_frame(pub) -> None:
        fault = next(faults, None)
        if fault:
            made[0].instrument.inject(fault)

    def drain() -> None:
        deadline = time.monotonic() + 120
        while len(got) < 13 and time.monotonic() < deadline:  # 12 frames and the end-of-run notice
            if pull.poll(100):
                got.append(pull.recv_multipart())

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    pub = run_acquisition(st, on_frame=on_frame)
    reader.join(130)
    metrics = httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=5).text
    pull.close(0)
    ctx.term()
    assert pub.seq == 12 and pub.published == 12
    frames = [decode_frame(parts) for parts in got if parts[0] == FRAME_TOPIC]
    assert [f.seq for f in frames] == list(range(12)) and len({f.run for f in frames}) == 1
    for f in frames:  # every frame whole, at the rate asked, with the bench's tone plan
        assert f.samples.shape == (1, 10_000) and f.fs_hz == pytest.approx(5e9)
        assert list(f.tones_hz) == pytest.approx([500e6, 700e6, 950e6], rel=1e-12)
        assert int(f.samples.max()) > int(f.samples.min())
    for reason in ("garbled_block", "timeout", "block_size", "record_length", "sample_rate", "reference_unlocked"):
        assert f'mtcw_acquisition_errors_total{{reason="{reason}"}} 1.0' in metrics, reason
    # gone and truncated both stop a block part-way (gone may also refuse the reconnection)
    assert 'mtcw_acquisition_errors_total{reason="transfer_incomplete"} 2.0' in metrics
    assert "mtcw_acquisitions_missed_total 2.0" in metrics
    assert 'mtcw_frames_published_total 12.0' in metrics
