"""services.ordering: reordering by seq, gap and end-of-run accounting (pure, no sockets)."""

from __future__ import annotations

from dataclasses import dataclass

from services.ordering import GapCounter, Reorderer


@dataclass(frozen=True)
class _Point:
    """The least a reorderer needs of a message (a PointMessage has it too)."""

    source: str
    seq: int
    t_ns: int
    run: int | None = None


def _msg(seq, t_ns=None, source="s", run=None):
    return _Point(source, seq, 1000 + seq if t_ns is None else t_ns, run)


def test_reorderer_releases_in_order_exactly_once():
    out = []
    r = Reorderer(lambda m: out.append(m.seq), timeout_s=1.0)
    for s in [0, 2, 1, 4, 3, 5]:
        r.add(_msg(s), now=0.0)
    assert out == [0, 1, 2, 3, 4, 5] and r.dropped == 0 and r.held() == 0


def test_reorderer_counts_a_gap_after_the_timeout_and_ignores_the_late_point():
    out = []
    r = Reorderer(lambda m: out.append(m.seq), timeout_s=1.0)
    for s in [0, 1, 3, 4]:
        r.add(_msg(s), now=0.0)
    assert out == [0, 1]
    r.poll(now=0.5)
    assert out == [0, 1]
    r.poll(now=1.5)
    assert out == [0, 1, 3, 4] and r.dropped == 1
    assert r.add(_msg(2), now=2.0) == "stale"  # arrived after its slot was given up: not released
    assert r.add(_msg(4), now=2.0) == "stale"  # a repeat
    assert out == [0, 1, 3, 4] and r.stale == 2


def test_reorderer_gives_up_when_too_many_are_held():
    out = []
    r = Reorderer(lambda m: out.append(m.seq), timeout_s=100.0, max_held=3)
    for s in [0, 2, 3, 4, 5]:
        r.add(_msg(s), now=0.0)
    assert out == [0, 2, 3, 4, 5] and r.dropped == 1


def test_reorderer_follows_a_publisher_restart_and_refuses_old_frames():
    out = []
    r = Reorderer(lambda m: out.append((m.seq, m.t_ns)), timeout_s=1.0)
    for s in [0, 1, 2, 4]:
        r.add(_msg(s, t_ns=100 + s, run=7), now=0.0)
    # a new run (new id, later trigger); its seq 1 overtakes its seq 0 (two workers)
    assert r.add(_msg(1, t_ns=501, run=8), now=0.1) == "restart"
    r.add(_msg(0, t_ns=500, run=8), now=0.1)
    assert r.add(_msg(3, t_ns=103, run=7), now=0.1) == "stale"  # the previous run's frame, late: not new
    assert r.add(_msg(2, t_ns=502, run=8), now=0.1) == "released"
    assert out == [(0, 100), (1, 101), (2, 102), (4, 104), (0, 500), (1, 501), (2, 502)]
    assert r.restarts == 1 and r.dropped == 1  # seq 3 of the old run never made it in time


def test_reorderer_without_run_ids_detects_restart_from_time():
    out = []
    r = Reorderer(lambda m: out.append(m.seq), timeout_s=1.0)
    for s in range(5):
        r.add(_msg(s, t_ns=100 + s), now=0.0)
    assert r.add(_msg(0, t_ns=500), now=0.1) == "restart"
    assert r.add(_msg(1, t_ns=102), now=0.1) == "stale"
    assert out == [0, 1, 2, 3, 4, 0]


def test_reorderer_counts_the_lost_tail_of_a_run_after_its_end_notice():
    out = []
    r = Reorderer(lambda m: out.append(m.seq), timeout_s=1.0)
    for s in [0, 1, 2, 4]:  # 3 is late, 5..9 never come
        r.add(_msg(s, run=7), now=0.0)
    assert r.end("s", 7, frames=10, t_ns=2000, now=0.2) == "ended"
    assert r.awaited() == 6 and r.dropped == 0  # 3 and 5..9
    r.add(_msg(3, run=7), now=0.5)
    r.poll(now=1.0)
    assert r.dropped == 0  # the timeout counts from the notice
    r.poll(now=1.3)
    assert out == [0, 1, 2, 3, 4] and r.dropped == 5 and r.awaited() == 0
    assert r.add(_msg(7, run=7), now=1.4) == "stale"  # a tail frame after its slot was given up
    assert r.end("s", 3, frames=4, t_ns=50, now=1.5) == "stale"  # an older run's notice changes nothing
    assert r.dropped == 5


def test_reorderer_end_notice_of_a_run_it_never_saw_counts_every_frame():
    r = Reorderer(lambda m: None, timeout_s=1.0)
    r.add(_msg(0, t_ns=100, run=1), now=0.0)
    assert r.end("s", 2, frames=3, t_ns=900, now=0.1) == "ended"  # new run: none of its frames came
    r.poll(now=1.2)
    assert r.dropped == 3 and r.restarts == 1


def test_gap_counter():
    g = GapCounter()
    gaps = [g.see("a", s) for s in [5, 6, 9, 10, 0, 1]]  # 0 after 10: restart, re-sync
    assert gaps == [0, 0, 2, 0, 0, 0] and g.dropped == 2 and g.received == 6
