"""services.history, the API's SQLite store: schema and query plans, ``since_seq`` across runs and
sources, retention, one process per file, damaged and newer files; restarts of the point store in
process; and restarts of a real ``mtcw api`` process, stopped cleanly and killed (SIGKILL), with
the books checked against what was published.

``python -m tests.test_history`` prints the store's throughput (points/s through ordering and
batched commits).
"""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest
import zmq

from services import history
from services.api import Metrics, PointStore
from services.history import HistoryDB, StoreError
from services.settings import ApiSettings, load
from services.sockets import wait_for_endpoints
from services.wire import encode_end, encode_points, end_message

from .test_api import T0_NS, _point

ROOT = Path(__file__).resolve().parents[1]


def _store(path: Path | str, clock_ns=lambda: T0_NS, **kw) -> PointStore:
    st = ApiSettings(**{"points_endpoint": "tcp://127.0.0.1:0", "reorder_timeout_s": 1.0, "store_path": str(path),
                        **kw})
    return PointStore(st, Metrics(), clock_ns=clock_ns)


def _seqs(store: PointStore, **kw) -> list[tuple[str, int]]:
    docs, _, _ = store.db.points(kw.get("since_seq", -1), kw.get("limit", 10_000), kw.get("source"))
    return [(p["source"], p["seq"]) for p in map(json.loads, docs)]


# ---------------------------------------------------------------------------------------------
# the store itself
def test_history_query_is_an_index_seek_per_segment(tmp_path):
    db = HistoryDB(tmp_path / "s.sqlite3", retention_points=100)
    try:
        plan = " ".join(r[-1] for r in db.conn.execute(
            "EXPLAIN QUERY PLAN SELECT id, body FROM points WHERE source = ? AND segment = ? AND seq > ? ORDER BY seq",
            ("a", 0, 5)))
        assert "USING INDEX points_by_segment (source=? AND segment=? AND seq>?)" in plan, plan
        assert "TEMP B-TREE" not in plan and "SCAN" not in plan, plan
        plan = " ".join(r[-1] for r in db.conn.execute(
            "EXPLAIN QUERY PLAN SELECT id, body FROM points INDEXED BY points_by_segment_id WHERE source = ? AND "
            "segment = ? AND id >= ? ORDER BY id", ("a", 0, 5)))
        assert "USING INDEX points_by_segment_id (source=? AND segment=? AND rowid>?)" in plan, plan
        assert "TEMP B-TREE" not in plan and "SCAN" not in plan, plan
        plan = " ".join(r[-1] for r in db.conn.execute(
            "EXPLAIN QUERY PLAN SELECT id, body FROM points WHERE id > ? ORDER BY id", (5,)))
        assert "SEARCH points USING INTEGER PRIMARY KEY (rowid>?)" in plan, plan
        plan = " ".join(r[-1] for r in db.conn.execute(
            "EXPLAIN QUERY PLAN SELECT source, segment FROM segments WHERE max_seq > ? AND last_id > ? AND source = ?",
            (5, 0, "a")))
        assert "SEARCH segments USING PRIMARY KEY (source=?)" in plan, plan
        assert db.conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert db.conn.execute("PRAGMA synchronous").fetchone()[0] == 1  # NORMAL
    finally:
        db.close()


def test_since_seq_across_runs_and_sources_is_release_order(tmp_path):
    """Two sources interleaved, one of them restarting (its seq starts again at 0): every query
    answers what a filter over the release order would."""
    store = _store(tmp_path / "s.sqlite3")
    try:
        released = []
        for i in range(30):
            store.add(_point(i, source="a", run=1, t_ns=T0_NS + i), now_mono=0.0)
            released.append(("a", i))
            if i % 3 == 0:
                store.add(_point(i // 3, source="b", run=5, t_ns=T0_NS + i), now_mono=0.0)
                released.append(("b", i // 3))
            if i % 7 == 0:
                store.flush()  # segments span commits
        for i in range(20):  # source a restarts: a new run, seq from 0
            store.add(_point(i, source="a", run=2, t_ns=T0_NS + 100 + i), now_mono=0.0)
            released.append(("a", i))
        store.flush()
        for source in (None, "a", "b", "c"):
            for since in (-1, 0, 5, 9, 15, 28, 29, 40):
                want = [(s, q) for s, q in released if q > since and (source is None or s == source)]
                for limit in (1, 7, 1000):
                    docs, more, _ = store.db.points(since, limit, source)
                    got = [(p["source"], p["seq"]) for p in map(json.loads, docs)]
                    assert got == want[:limit] and more == (len(want) > limit), (source, since, limit)
                    pages, after = [], 0  # paged by the cursor: the same points, each once
                    while True:
                        docs, more, nxt = store.db.points(since, limit, source, after)
                        pages += [(p["source"], p["seq"]) for p in map(json.loads, docs)]
                        if not more:
                            break
                        after = nxt
                    assert pages == want, (source, since, limit)
    finally:
        store.close()


def test_retention_by_count_deletes_the_oldest_in_batches(tmp_path, monkeypatch):
    monkeypatch.setattr(history, "RETENTION_BATCH", 30)
    store = _store(tmp_path / "s.sqlite3", retention_points=100)
    try:
        for i in range(200):
            store.add(_point(i, run=1), now_mono=0.0)
        store.flush()
        assert store.db.rows == 170 and _seqs(store)[0] == ("bench", 30)  # one batch deleted, not all at once
        rows = []
        for _ in range(4):
            store.db.write([], {}, {}, T0_NS)  # the idle heartbeat goes on deleting
            rows.append(store.db.rows)
        assert rows == [140, 110, 100, 100]
        assert [q for _, q in _seqs(store)] == list(range(100, 200))
        assert store.db.conn.execute("SELECT count(*) FROM points").fetchone()[0] == 100
        assert store.latest["bench"].seq == 199
    finally:
        store.close()


def test_retention_by_age_and_empty_segments_go(tmp_path):
    now = [T0_NS]
    store = _store(tmp_path / "s.sqlite3", clock_ns=lambda: now[0], retention_s=10.0)
    try:
        for i in range(50):
            store.add(_point(i, source="old", run=1), now_mono=0.0)
        store.flush()
        now[0] += 20 * 10**9
        for i in range(50):
            store.add(_point(i, source="new", run=1, t_ns=now[0] - 10**6), now_mono=0.0)
        store.flush()  # the old points are 20 s old: deleted in this commit
        assert store.db.rows == 50 and {s for s, _ in _seqs(store)} == {"new"}
        segs = store.db.conn.execute("SELECT source FROM segments").fetchall()
        assert segs == [("new",)]
        assert set(store.latest) == {"old", "new"}  # the newest point of each source stays
    finally:
        store.close()


def test_one_process_per_store_file(tmp_path):
    a = HistoryDB(tmp_path / "s.sqlite3", retention_points=10)
    try:
        with pytest.raises(StoreError, match=rf"store_path: .* in use by another process \(pid {os.getpid()}\)"):
            HistoryDB(tmp_path / "s.sqlite3", retention_points=10)
    finally:
        a.close()
    HistoryDB(tmp_path / "s.sqlite3", retention_points=10).close()  # free again once closed


def test_a_damaged_file_is_moved_aside_and_a_newer_schema_refused(tmp_path):
    path = tmp_path / "s.sqlite3"
    path.write_bytes(b"this is not an SQLite database" * 100)
    db = HistoryDB(path, retention_points=10)
    try:
        assert db.rows == 0
        aside = list(tmp_path.glob("s.sqlite3.corrupt-*"))
        assert len(aside) == 1 and aside[0].read_bytes().startswith(b"this is not")
    finally:
        db.close()
    with sqlite3.connect(path) as c:
        c.execute("PRAGMA user_version = 99")
    with pytest.raises(StoreError, match="schema version 99, made by a newer mtcw"):
        HistoryDB(path, retention_points=10)
    other = tmp_path / "other.sqlite3"
    with sqlite3.connect(other) as c:
        c.execute("CREATE TABLE t (x)")
    with pytest.raises(StoreError, match="SQLite file of something else"):
        HistoryDB(other, retention_points=10)


def test_store_settings_name_their_field(tmp_path):
    with pytest.raises(ValueError, match="store_path: .* is a directory"):
        load(ApiSettings, store_path=str(tmp_path))
    with pytest.raises(ValueError, match="max_seq_jump: 100 is less than reorder_max"):
        load(ApiSettings, max_seq_jump=100)
    # "~name" of no such user: pathlib raised RuntimeError (found by test_fuzz's settings fuzzing, "~0")
    with pytest.raises(ValueError, match=r"store_path: '~no-such-user-0/h\.sqlite3': no home directory to expand"):
        load(ApiSettings, store_path="~no-such-user-0/h.sqlite3")
    # reorder_max alone past the default jump: the error names reorder_max, the field given (found by
    # test_fuzz's settings fuzzing)
    with pytest.raises(ValueError, match=r"^reorder_max: 100001 is more than max_seq_jump"):
        load(ApiSettings, reorder_max=100001)
    with pytest.raises(ValueError, match="retention_s"):
        load(ApiSettings, retention_s=-1)
    assert load(ApiSettings, history=500).retention_points == 500  # the old name still works
    assert load(ApiSettings, history=500, retention_points=700).retention_points == 700
    made = tmp_path / "a" / "b" / "s.sqlite3"
    db = HistoryDB(made, retention_points=10)  # parents created
    db.close()
    assert made.exists()


def test_memory_stores_are_private_and_leave_no_file(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    a, b = _store(":memory:"), _store(":memory:")
    try:
        a.add(_point(0), now_mono=0.0)
        a.flush()
        assert _seqs(a) == [("bench", 0)] and _seqs(b) == [] and not a.db.durable
        assert "not durable" in a.store_status(receiver_running=False)[1]
    finally:
        a.close()
        b.close()
    assert list(tmp_path.iterdir()) == []
    again = _store(":memory:")  # a new one starts empty
    try:
        assert _seqs(again) == [] and again.snapshot()["received"] == 0
    finally:
        again.close()


# ---------------------------------------------------------------------------------------------
# restarts in process
def test_a_clean_restart_keeps_history_latest_counts_and_held_points(tmp_path):
    path = tmp_path / "s.sqlite3"
    a = _store(path)
    for s in (0, 1, 2, 3, 4, 6, 7):  # 5 is late: 6 and 7 are held for it
        a.add(_point(s, run=9), now_mono=0.0)
    a.add(_point(300, source="other", run=1), now_mono=0.0)  # joined late: served at once
    a.close()

    b = _store(path)
    try:
        snap = b.snapshot()
        assert (snap["received"], snap["processed"], snap["held_for_reordering"]) == (8, 6, 2)
        assert b.latest["bench"].seq == 4 and b.latest["other"].seq == 300
        assert "mtcw_frames_received_total 8.0" in _metrics(b)
        assert b.add(_point(3, run=9), now_mono=1.0) == "stale"  # served before the restart: not new
        assert b.add(_point(5, run=9), now_mono=1.0) == "released"  # releases the held 6 and 7
        b.flush()
        assert [q for s, q in _seqs(b, source="bench")] == list(range(8))
        snap = b.snapshot()
        assert (snap["received"], snap["processed"], snap["rejected"], snap["held_for_reordering"]) == (10, 9, 1, 0)
        assert snap["received"] == snap["processed"] + snap["rejected"]
    finally:
        b.close()


def test_a_held_point_that_cannot_be_read_back_becomes_a_gap(tmp_path):
    """Unreadable after the restart: out of ``received``, its seq dropped; the books balance."""
    path = tmp_path / "s.sqlite3"
    a = _store(path)
    for s in (0, 2, 3):  # 2 and 3 held for 1
        a.add(_point(s, run=9), now_mono=0.0)
    a.close()
    with sqlite3.connect(path) as c:
        c.execute("UPDATE held SET body = x'c1' WHERE seq = 2")
    b = _store(path)
    try:
        snap = b.snapshot()
        assert (snap["received"], snap["processed"], snap["rejected"], snap["held_for_reordering"]) == (2, 1, 0, 1)
        assert 'mtcw_store_errors_total{kind="bad_row"} 1.0' in _metrics(b)
        b.add(_point(1, run=9), now_mono=time.monotonic())  # releases 1; 2 is a gap now; 3 waits
        b.poll(time.monotonic() + 5)
        b.flush()
        snap = b.snapshot()
        assert (snap["received"], snap["processed"], snap["rejected"], snap["dropped"]) == (3, 3, 0, 1)
        assert snap["processed"] + snap["rejected"] + snap["dropped"] == 4  # seqs 0 .. 3
        assert b.db.conn.execute("SELECT count(*) FROM held").fetchone()[0] == 0  # the bad row went too
    finally:
        b.close()


def test_given_up_seqs_survive_a_restart_so_a_late_point_is_counted_once(tmp_path):
    path = tmp_path / "s.sqlite3"
    a = _store(path)
    now = time.monotonic()
    for s in (0, 1, 3):
        a.add(_point(s, run=2), now_mono=now)
    a.poll(now + 1.5)  # 2 given up: dropped
    a.close()
    b = _store(path)
    try:
        assert b.add(_point(2, run=2), now_mono=time.monotonic()) == "late"
        assert b.add(_point(2, run=2), now_mono=time.monotonic()) == "stale"  # once late, then a repeat
        b.flush()
        snap = b.snapshot()
        assert (snap["received"], snap["processed"], snap["rejected"], snap["dropped"], snap["late"]) == (4, 3, 1, 1, 1)
        assert "mtcw_frames_late_total 1.0" in _metrics(b)
    finally:
        b.close()


def test_what_was_not_committed_is_lost_and_counted_dropped_after_restart(tmp_path):
    """A kill loses what came after the last commit; the restarted store counts those frames as
    dropped (seq gaps), so that published = processed + rejected + dropped."""
    path = tmp_path / "s.sqlite3"
    a = _store(path)
    for s in range(10):
        a.add(_point(s, run=4), now_mono=0.0)
    a.flush()
    for s in range(10, 15):
        a.add(_point(s, run=4), now_mono=0.0)
    assert a.latest["bench"].seq == 9  # never shown: not committed
    a.db.close()  # the process dies here: no commit

    b = _store(path)
    try:
        assert b.snapshot()["received"] == 10 and b.latest["bench"].seq == 9
        now = time.monotonic()  # the restored state's timers started at the restart, by this clock
        for s in range(15, 20):
            b.add(_point(s, run=4), now_mono=now)
        b.end(end_message("bench", 4, frames=22, t_ns=T0_NS + 30, dropped=0), now_mono=now)
        b.poll(now_mono=now + 1.5)
        b.flush()
        snap = b.snapshot()
        assert (snap["received"], snap["processed"], snap["rejected"], snap["dropped"]) == (15, 15, 0, 7)
        assert snap["processed"] + snap["rejected"] + snap["dropped"] == 22  # every frame published
        assert [q for _, q in _seqs(b)] == list(range(10)) + list(range(15, 20))
    finally:
        b.close()


def _metrics(store: PointStore) -> str:
    from prometheus_client import generate_latest

    return generate_latest(store.m.registry).decode()


# ---------------------------------------------------------------------------------------------
# throughput
def measure_throughput(path: Path | str, points: int = 20_000, batch: int = 500) -> float:
    """Points per second through the point store: ordering, counting and one commit per ``batch``
    points (as the receiver commits once per loop iteration), into the SQLite file ``path``."""
    store = _store(path, retention_points=points)
    try:
        msgs = [_point(s, run=1) for s in range(points)]
        t0 = time.perf_counter()
        for i, m in enumerate(msgs, 1):
            store.add(m, now_mono=0.0)
            if i % batch == 0:
                store.commit(now_mono=float(i))
        store.flush()
        dt = time.perf_counter() - t0
        assert store.db.rows == points and store.snapshot()["processed"] == points
    finally:
        store.close()
    return points / dt


def test_store_takes_more_than_1000_points_per_second(tmp_path):
    rate = measure_throughput(tmp_path / "s.sqlite3", points=5000, batch=100)
    assert rate > 1000, f"{rate:.0f} points/s"


# ---------------------------------------------------------------------------------------------
# a real `mtcw api` process, restarted
class ApiProcess:
    """``python -m services.cli api`` on port 0 (HTTP and points), store ``store``."""

    def __init__(self, tmp: Path, store: Path, name: str) -> None:
        self.report = tmp / f"{name}.endpoints.json"
        env = {**os.environ, "MTCW_POINTS_ENDPOINT": "tcp://127.0.0.1:0", "MTCW_ENDPOINTS_FILE": str(self.report),
               "MTCW_STORE_PATH": str(store), "MTCW_REORDER_TIMEOUT_S": "0.5", "PYTHONUNBUFFERED": "1"}
        self.log = tmp / f"{name}.log"
        self.proc = subprocess.Popen([sys.executable, "-m", "services.cli", "api", "--port", "0"], cwd=ROOT, env=env,
                                     stdout=open(self.log, "wb"), stderr=subprocess.STDOUT)
        got = wait_for_endpoints(self.report, 60, alive=lambda: self.proc.poll() is None)
        self.http, self.points = got["http_url"], got["points_endpoint"]

    def get(self, path: str, **params) -> httpx.Response:
        return httpx.get(f"{self.http}{path}", params=params, timeout=5)

    def health(self) -> dict:
        return self.get("/healthz").json()

    def history(self) -> list[int]:
        return [p["seq"] for p in self.get("/v1/points", limit=10_000).json()["points"]]

    def wait(self, cond, what: str, timeout: float = 60) -> dict:
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            h = self.health()
            if cond(h):
                return h
            time.sleep(0.02)
        raise AssertionError(f"timed out waiting for {what}: {self.health()}\n{self.log.read_text()[-3000:]}")

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@pytest.fixture
def apis():
    started: list[ApiProcess] = []
    yield started
    for a in started:
        a.close()


def _pusher(ctx: zmq.Context, endpoint: str) -> zmq.Socket:
    push = ctx.socket(zmq.PUSH)
    push.setsockopt(zmq.LINGER, 0)
    push.setsockopt(zmq.SNDTIMEO, 2000)
    push.connect(endpoint)
    return push


def _accounted(published: int):
    return lambda h: h["processed"] + h["rejected"] + h["dropped"] >= published and h["held_for_reordering"] == 0


def test_api_process_stopped_cleanly_keeps_everything_and_counts_what_it_missed(tmp_path, ctx, apis):
    store = tmp_path / "api.sqlite3"
    a = ApiProcess(tmp_path, store, "a")
    apis.append(a)
    push = _pusher(ctx, a.points)
    for s in range(50):
        push.send_multipart(encode_points(_point(s, run=7)))
    a.wait(lambda h: h["processed"] == 50, "50 points")
    second = subprocess.run([sys.executable, "-m", "services.cli", "api", "--port", "0"], cwd=ROOT, timeout=60,
                            capture_output=True, text=True, env={**os.environ, "MTCW_STORE_PATH": str(store),
                                                                 "MTCW_POINTS_ENDPOINT": "tcp://127.0.0.1:0"})
    assert second.returncode != 0 and f"store_path: {store} is in use by another process (pid {a.proc.pid})" \
        in second.stderr, second.stderr[-2000:]
    a.proc.send_signal(signal.SIGTERM)
    assert a.proc.wait(20) in (0, -signal.SIGTERM), a.log.read_text()[-2000:]
    push.close()
    # seq 50 .. 59 are published while the API is down: nobody receives them
    b = ApiProcess(tmp_path, store, "b")
    apis.append(b)
    h = b.health()
    assert (h["received"], h["processed"], h["rejected"], h["dropped"]) == (50, 50, 0, 0)
    assert b.history() == list(range(50)) and b.get("/v1/points/latest", source="bench").json()["seq"] == 49
    assert "mtcw_frames_processed_total 50.0" in b.get("/metrics").text
    push = _pusher(ctx, b.points)
    for s in range(60, 70):
        push.send_multipart(encode_points(_point(s, run=7)))
    push.send_multipart(encode_points(_point(40, run=7)))  # a repeat of a point served before the restart
    push.send_multipart(encode_end(end_message("bench", 7, frames=70, t_ns=T0_NS + 100, dropped=0)))
    h = b.wait(_accounted(71), "every frame accounted for")
    assert (h["received"], h["processed"], h["rejected"], h["dropped"]) == (61, 60, 1, 10)
    assert b.history() == list(range(50)) + list(range(60, 70))  # the repeat is stale, not new
    assert "mtcw_frames_dropped_total 10.0" in b.get("/metrics").text
    push.close()


def test_api_process_killed_keeps_its_last_commit_and_the_books_balance(tmp_path, ctx, apis):
    """SIGKILL in the middle of a burst: the restarted API has everything the killed one had
    shown (it shows only what is committed), nothing twice, and counts every frame it never got
    as dropped."""
    store = tmp_path / "api.sqlite3"
    a = ApiProcess(tmp_path, store, "a")
    apis.append(a)
    burst = 50_000
    sent = [0]

    def pump() -> None:
        push = _pusher(ctx, a.points)
        try:
            for s in range(burst):
                push.send_multipart(encode_points(_point(s, run=3)))
                sent[0] = s + 1
        except zmq.Again:  # the API is gone: what is queued here is lost, like a worker's
            pass
        finally:
            push.close()

    t = threading.Thread(target=pump)
    t.start()
    shown = a.wait(lambda h: h["processed"] >= 2000, "the burst under way")["processed"]
    a.proc.send_signal(signal.SIGKILL)
    a.proc.wait(10)
    t.join(30)
    b = ApiProcess(tmp_path, store, "b")
    apis.append(b)
    h0 = b.health()
    kept = h0["processed"]
    assert kept >= shown, "a point was shown before the kill that the restart took back"
    assert h0["received"] == kept + h0["held_for_reordering"] and h0["rejected"] == h0["dropped"] == 0
    assert b.history() == list(range(kept))
    # the publisher goes on; then its end-of-run notice
    push = _pusher(ctx, b.points)
    for s in range(burst, burst + 100):
        push.send_multipart(encode_points(_point(s, run=3)))
    push.send_multipart(encode_end(end_message("bench", 3, frames=burst + 100, t_ns=T0_NS + 10**6, dropped=0)))
    h = b.wait(_accounted(burst + 100), "every frame accounted for")
    push.close()
    seqs = b.history()
    assert seqs == sorted(set(seqs)) and seqs[:kept] == list(range(kept))  # nothing twice, in order
    assert h["received"] == h["processed"] + h["rejected"] and h["rejected"] == 0
    assert h["processed"] + h["rejected"] + h["dropped"] == burst + 100  # published = processed + rejected + dropped
    assert len(seqs) == h["processed"] and seqs[-100:] == list(range(burst, burst + 100))
    print(f"\nSIGKILL: shown {shown} before the kill, {kept} committed and restored, {sent[0]} of {burst} sent "
          f"before the API was gone; after the restart processed {h['processed']}, dropped {h['dropped']}")


def measure_end_to_end(tmp: Path, points: int = 20_000) -> float:
    """Points per second pushed into the points socket of a running ``mtcw api`` until all are
    processed and shown (decode, order, commit)."""
    api = ApiProcess(tmp, tmp / "e2e.sqlite3", "e2e")
    ctx = zmq.Context()
    try:
        push = _pusher(ctx, api.points)
        msgs = [encode_points(_point(s, run=1)) for s in range(points)]
        t0 = time.monotonic()
        for m in msgs:
            push.send_multipart(m)
        api.wait(lambda h: h["processed"] == points, "every point", 300)
        push.close()
        return points / (time.monotonic() - t0)
    finally:
        api.close()
        ctx.destroy(linger=0)


if __name__ == "__main__":
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        for batch in (10, 100, 1000):
            r = measure_throughput(Path(d) / f"t{batch}.sqlite3", points=20_000, batch=batch)
            print(f"store throughput, {batch} points per commit: {r:,.0f} points/s")
        print(f"end to end, through the points socket of a running mtcw api: {measure_end_to_end(Path(d)):,.0f} "
              f"points/s")
