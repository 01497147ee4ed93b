"""mtcw_bench/stream.py: CPU per frame from /proc (a synthetic tree, and this process against
the kernel's own accounting), spreads and ratios of repeated windows, the CPU-bound projection,
and the report's keys."""

from __future__ import annotations

import math
import os
import time

import pytest

from mtcw_bench import stream as B


def _stat_line(pid: int, comm: str, utime: int, stime: int) -> str:
    # fields 1..: pid (comm) state ppid pgrp session tty_nr tpgid flags minflt cminflt majflt cmajflt utime stime ...
    rest = ["S", "1", "1", "1", "0", "-1", "4194560", "10", "0", "0", "0", str(utime), str(stime), "7", "9"] + ["0"] * 37
    return f"{pid} ({comm}) " + " ".join(rest) + "\n"


def test_read_cpu_s_on_a_synthetic_proc(tmp_path):
    """utime + stime (fields 14, 15) over the clock tick; a command name with spaces and ')' does
    not shift the fields."""
    (tmp_path / "42").mkdir()
    (tmp_path / "42" / "stat").write_text(_stat_line(42, "python -m x) (y", 250, 50))
    assert B.read_cpu_s(42, tmp_path, clk_tck=100) == pytest.approx(3.0)
    (tmp_path / "43").mkdir()
    (tmp_path / "43" / "stat").write_text("43 (short) S 1")
    with pytest.raises(ValueError, match="fields"):
        B.read_cpu_s(43, tmp_path, clk_tck=100)
    with pytest.raises(OSError):
        B.read_cpu_s(44, tmp_path, clk_tck=100)
    # a process that is gone is left out of a snapshot, the others kept
    assert B.cpu_snapshot({"api": 42, "gone": 44}, tmp_path, clk_tck=100) == {"api": pytest.approx(3.0)}


def test_read_cpu_s_agrees_with_the_kernels_accounting_of_this_process():
    """The /proc reading of this process moves with ``os.times`` (the same counters through
    another call) over a busy second, to within two clock ticks."""
    tck = os.sysconf("SC_CLK_TCK")

    def both():
        t = os.times()
        return B.read_cpu_s(os.getpid()), t.user + t.system

    a0, b0 = both()
    t_end = time.process_time() + 0.3
    while time.process_time() < t_end:
        sum(range(1000))
    a1, b1 = both()
    assert a1 - a0 >= 0.2
    assert abs((a1 - a0) - (b1 - b0)) <= 2 / tck + 1e-9


def test_machine_busy_s_on_a_synthetic_proc_stat(tmp_path):
    # user nice system idle iowait irq softirq steal guest guest_nice
    (tmp_path / "stat").write_text("cpu  100 5 20 1000 30 1 2 3 0 0\ncpu0 50 2 10 500 15 0 1 1 0 0\n")
    assert B.machine_busy_s(tmp_path, clk_tck=100) == pytest.approx((100 + 5 + 20 + 1 + 2 + 3) / 100)
    (tmp_path / "stat").write_text("intr 1 2 3\n")
    with pytest.raises(ValueError, match="cpu"):
        B.machine_busy_s(tmp_path, clk_tck=100)


def test_cpu_per_frame_and_cores():
    got = B.cpu_per_frame({"acq": 10.0, "w0": 100.0, "gone": 1.0}, {"acq": 10.5, "w0": 109.0}, 300, 10.0)
    assert set(got) == {"acq", "w0"}
    assert got["acq"]["cpu_s_per_frame"] == pytest.approx(0.5 / 300)
    assert got["w0"]["cpu_s_per_frame"] == pytest.approx(0.03) and got["w0"]["cores"] == pytest.approx(0.9)
    assert B.cpu_per_frame({"a": 1.0}, {"a": 2.0}, 0, 1.0)["a"]["cpu_s_per_frame"] is None


def test_spread_and_ratio_of_repeated_windows():
    s1 = B.spread([20.0, 21.0, 19.0])
    assert (s1["median"], s1["min"], s1["max"]) == (20.0, 19.0, 21.0) and s1["spread"] == pytest.approx(0.1)
    s2 = B.spread([38.0, 38.5, 37.5])
    r = B.ratio_with_spread(s2, s1, 1.6)
    assert r["ratio"] == pytest.approx(38 / 20) and r["lo"] == pytest.approx(37.5 / 21)
    assert r["hi"] == pytest.approx(38.5 / 19) and r["met"] and r["short_by"] == 0
    assert r["noisy"] == ((r["hi"] - r["lo"]) / r["ratio"] > B.NOISY_SPREAD) and r["noisy"]  # 13 % wide
    tight = B.ratio_with_spread(B.spread([30.0, 30.3]), B.spread([20.0, 20.1]), 1.6)
    assert not tight["noisy"] and not tight["met"] and tight["short_by"] == pytest.approx(1.6 - 30.15 / 20.05)
    assert B.ratio_with_spread(B.spread([]), s1, 1.6)["ratio"] is None


def test_projection_from_cpu_per_frame():
    """Two workers at 30 ms of CPU a frame, acquisition + API 2 ms: two cores give 2 / 32 ms =
    62.5 frames/s (the cores bind), one worker 1 / 30 ms = 33.3 (the worker binds)."""
    def cpu(workers: int) -> dict:
        d = {"acq": {"cpu_s_per_frame": {"median": 0.0015}}, "api": {"cpu_s_per_frame": {"median": 0.0005}},
             "workers_total": {"cpu_s_per_frame": {"median": 0.030}}}
        d.update({f"w{i}": {"cpu_s_per_frame": {"median": 0.030 / workers}} for i in range(workers)})
        return d

    assert B.projected_frames_per_s(cpu(1), 1, 2) == pytest.approx(1 / 0.030)
    assert B.projected_frames_per_s(cpu(2), 2, 2) == pytest.approx(2 / 0.032)
    assert B.projected_frames_per_s(cpu(4), 4, 2) == pytest.approx(2 / 0.032)
    assert B.projected_frames_per_s({}, 2, 2) is None


def test_markdown_states_targets_with_their_spread():
    def row(w: int, fps: list[float], p50: float, p99: float) -> dict:
        thr = {"frames_per_s": B.spread(fps)["median"], "frames_per_s_spread": B.spread(fps), "chain_median_s": 0.03,
               "cpu": {"acq": {"cpu_s_per_frame": B.spread([0.001]), "cores": B.spread([0.03])},
                       "workers_total": {"cpu_s_per_frame": B.spread([0.03])}},
               "other_cores": 0.1, "projected_frames_per_s": 33.0}
        lat = {"rate_hz": 0.8 * thr["frames_per_s"], "dropped": 0, "latency_p50_s": p50, "latency_p99_s": p99,
               "latency_p50_s_spread": B.spread([p50]), "latency_p99_s_spread": B.spread([p99])}
        return {"workers": w, "threads": 1, "throughput": thr, "latency_at_80pct": lat}

    rows = [row(1, [30, 31, 29], 0.04, 0.06), row(2, [45, 46, 44], 0.05, 0.2)]
    doc = {"command": "mtcw-bench-stream --seconds 1", "rows": rows,
           "machine": {"cores": 2, "platform": "x", "load_before": 1.0, "load_after": 2.0},
           "scaling": [{"workers": 2, "threads": 1, "projected_ratio": 1.9,
                        "ratio": B.ratio_with_spread(rows[1]["throughput"]["frames_per_s_spread"],
                                                     rows[0]["throughput"]["frames_per_s_spread"], 1.6)}]}
    md = B.markdown(doc)
    assert "| 2 workers ≥ 1.6× one worker's frames/s (threads 1) | 1.50× (1.42–1.59) noisy | missed by 0.10×" in md
    assert "projected from CPU per frame: 1.90×" in md
    assert "| p99 / p50, 1 worker(s) (threads 1) | 1.50 (1.50–1.50)× | no target (reported; < 3×) |" in md
    assert "| p99 < 3× p50, 2 worker(s) (threads 1) | 4.00 (4.00–4.00)× | missed by 1.00× |" in md
    # with the windows' ratios: their median and range, judged on the median, the worst window said
    rows[1]["latency_at_80pct"]["latency_p99_over_p50_spread"] = B.spread([1.2, 2.0, 4.9])
    md = B.markdown(doc)
    assert ("| p99 < 3× p50, 2 worker(s) (threads 1) | 2.00 (1.20–4.90)× noisy | met in the median window, not in all "
            "(4.90× in the worst) |") in md
    assert math.isclose(rows[1]["latency_at_80pct"]["rate_hz"], 36.0)


def test_a_ratio_without_a_target_is_reported_not_judged():
    r = B.ratio_with_spread(B.spread([40.0]), B.spread([20.0]), None)
    assert r["ratio"] == 2.0 and r["met"] is None and r["short_by"] is None and not r["noisy"]
