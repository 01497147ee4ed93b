"""Put results back in ``seq`` order and count what never came (pure Python, no sockets).

Several workers finish frames out of order; the consumer releases them in ``seq`` order per
source. A missing ``seq`` is waited for while the stream is stuck on it (no point arrived to
fill the next slot) for up to a timeout, or until too many later points are held; then it is
counted as dropped. A point that arrives after its slot was given up is ``late``: its frame is
already counted (as dropped), so it is counted apart, never released and never counted twice
(the given-up seqs are remembered, as at most :data:`MAX_GAPS` ranges per run, for the run in
progress and the one before it). A repeat of a released point is stale. A publisher restart starts a new run: the message's ``run`` id
changes (or, from a publisher that sends none, ``seq`` goes back while the trigger time ``t_ns``
moves forward); a point of the previous run that arrives afterwards is stale, not new. An
end-of-run notice (:meth:`Reorderer.end`) tells how many frames the run had, so that frames lost
after the last one that arrived are counted as dropped as well.

Nothing a single message says can move the books by more than ``max_jump`` frames. Anyone who
can reach the points socket can send a point (unless CurveZMQ keys are configured), and a point
or notice is believed only within these bounds:

* a point whose ``seq`` is more than ``max_jump`` ahead of the next expected one is refused
  (:meth:`Reorderer.add` returns ``"jump"``; nothing is held, counted or released). A second
  refused point of the same run a little after it (within ``max_held`` seqs, triggered later)
  confirms the jump: the source re-synchronises there and the gap is counted as dropped, as any
  gap is. So a lone forged or corrupt seq (``2**62``) changes nothing, while a real stream that
  jumped (an API down for an hour while the node published on) loses one point, not the run;
* an end-of-run notice is believed only for the run in progress of its source, and only if its
  frame count is at least the next expected seq and at most ``max_jump`` beyond the highest seq
  seen (:meth:`Reorderer.end` returns ``"other_run"`` or ``"bad_frames"`` otherwise);
* a point held far ahead does not give up the gap before it while the stream is still filling
  that gap in order: gaps are declared when the stream is stuck, not when a held point is old.

A new run (new ``run`` id, later ``t_ns``) is still believed from one point, as a publisher
restart must be; the store in front of the reorderer bounds how far ahead of its clock ``t_ns``
may be (:class:`services.api.PointStore`), which bounds how long a forged new run can shadow the
real one.

The state of each source can be read (:meth:`Reorderer.sources`) and put back
(:meth:`Reorderer.restore`), so that a restarted consumer goes on where it stopped: what it missed
while it was down is a seq gap, counted as dropped.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Callable, Generic, Optional, Protocol, TypeVar


class Sequenced(Protocol):
    """What the reorderer reads of a message (a :class:`~services.wire.PointMessage` has it)."""

    @property
    def source(self) -> str: ...

    @property
    def seq(self) -> int: ...

    @property
    def t_ns(self) -> int: ...

    @property
    def run(self) -> Optional[int]: ...


M = TypeVar("M", bound=Sequenced)

#: Default bound (frames) on the gap one message may declare: 100 000 frames is an hour at 25
#: frames/s (the 1e6-sample bench rate) and 100 s at 1 kHz. Larger real jumps re-synchronise
#: after a second point (one point lost); smaller ones are ordinary gaps.
DEFAULT_MAX_JUMP = 100_000
#: Ranges of given-up seqs remembered per run (the oldest forgotten first): a late point of an
#: older range is counted stale (and its frame twice, as dropped and rejected).
MAX_GAPS = 1024


class Gaps:
    """Seqs given up as dropped: sorted, disjoint half-open ranges ``[a, b)``, the newest
    :data:`MAX_GAPS` of them.

    Parameters
    ----------
    ranges : iterable of (int, int), optional
        Ranges to start with (as :meth:`ranges` gave them).
    """

    def __init__(self, ranges: Iterable[tuple[int, int]] = ()) -> None:
        self._r: list[list[int]] = [[int(a), int(b)] for a, b in ranges if a < b]

    def add(self, a: int, b: int) -> None:
        """Seqs ``a .. b - 1`` were given up (after every range already here: gaps come in order)."""
        if a >= b:
            return
        if self._r and self._r[-1][1] == a:
            self._r[-1][1] = b
        else:
            self._r.append([a, b])
        if len(self._r) > MAX_GAPS:
            del self._r[0]

    def take(self, seq: int) -> bool:
        """Whether ``seq`` was given up (and is not any more: a late point comes once)."""
        i = bisect.bisect_right(self._r, seq, key=lambda r: r[0]) - 1
        if i < 0 or not self._r[i][0] <= seq < self._r[i][1]:
            return False
        a, b = self._r[i]
        self._r[i:i + 1] = [r for r in ([a, seq], [seq + 1, b]) if r[0] < r[1]]
        return True

    def ranges(self) -> list[tuple[int, int]]:
        return [(a, b) for a, b in self._r]

    def __len__(self) -> int:
        return sum(b - a for a, b in self._r)


@dataclass
class SourceState:
    """What the reorderer knows of one source (all of it is persisted by the API's store).

    Attributes
    ----------
    next_seq : int
        The next ``seq`` to release.
    run : int or None
        The run in progress (``None`` from a publisher that sends no run ids).
    max_t_ns : int
        Latest trigger time seen (Unix ns); a message of another run triggered at or before it is stale.
    floor_t_ns : int
        Without run ids: points triggered at or before this belong to an older run.
    held : dict
        ``seq -> (arrival time s, message)``: points waiting for a predecessor.
    end_seq : int or None
        The run's frame count, once its end-of-run notice came.
    end_at : float
        When that notice came (the caller's clock, s).
    progress_at : float
        When a point last filled the next slot (or the state began): gaps are given up when this
        and the oldest held point are older than the timeout.
    jump : tuple or None
        ``(seq, t_ns)`` of the last point refused for jumping ahead, awaiting confirmation.
    source : str
        The source's name.
    gaps : Gaps
        Seqs of this run given up as dropped.
    prev_run : int or None
        The run before this one.
    prev_gaps : Gaps or None
        Its given-up seqs (None: no run before this one is known).
    """

    next_seq: int
    run: int | None = None
    max_t_ns: int = 0
    floor_t_ns: int = -1
    held: dict[int, tuple[float, Sequenced]] = field(default_factory=dict)
    end_seq: int | None = None
    end_at: float = 0.0
    progress_at: float = 0.0
    jump: tuple[int, int] | None = None
    source: str = ""
    gaps: Gaps = field(default_factory=Gaps)
    prev_run: int | None = None
    prev_gaps: Gaps | None = None

    def horizon(self) -> int:
        """One past the highest seq seen (released or held)."""
        return max(self.next_seq, max(self.held) + 1) if self.held else self.next_seq


class Reorderer(Generic[M]):
    """Per-source reorder buffer of messages with ``source``, ``seq``, ``t_ns`` and ``run``.

    Parameters
    ----------
    release : callable(message)
        Called for every point, once, in ``seq`` order per source.
    timeout_s : float
        How long the stream may be stuck on a missing seq (with later points held) before the
        gap is given up.
    max_held : int
        Points held per source before the gap is given up regardless of time.
    max_jump : int
        The largest gap (frames) one message may declare: a point further ahead of the next
        expected seq, or an end-of-run notice further beyond the highest seq seen, is refused.
        At least ``max_held``.

    Attributes
    ----------
    dropped, stale, late, restarts, resyncs : int
        Frames given up; points refused as repeated, of an older run, or held beyond their run's
        end; points that came after their slot was given up (already counted in ``dropped``);
        new runs; confirmed jumps.
    dirty : set of str
        Sources whose state changed since the caller last cleared it (to persist them).
    """

    def __init__(self, release: Callable[[M], None], timeout_s: float = 2.0, max_held: int = 256,
                 max_jump: int = DEFAULT_MAX_JUMP) -> None:
        if max_jump < max_held:
            raise ValueError(f"max_jump ({max_jump}) must be at least max_held ({max_held})")
        self._release = release
        self.timeout_s = timeout_s
        self.max_held = max_held
        self.max_jump = max_jump
        self._src: dict[str, SourceState] = {}
        self.dropped = 0
        self.stale = 0
        self.late = 0
        self.restarts = 0
        self.resyncs = 0
        self.dirty: set[str] = set()

    def add(self, msg: M, now: float) -> str:
        """Offer one point.

        Returns
        -------
        str
            ``"held"``, ``"released"``, ``"restart"`` (a new run), ``"resync"`` (a confirmed jump),
            ``"late"`` (its slot was given up: counted in :attr:`late`, its frame already in
            :attr:`dropped`), ``"stale"`` (repeated or of an older run; counted in :attr:`stale`)
            or ``"jump"`` (refused: too far ahead; nothing counted here, the caller counts it).
        """
        source, seq, t_ns, run = msg.source, int(msg.seq), int(msg.t_ns), msg.run
        st, kind = self._run_state(source, seq, run, t_ns, now)
        if kind == "older":
            return self._late_or_stale(st, st.prev_gaps if run == st.prev_run else None, seq)
        outcome = "restart" if kind == "restart" else "held"
        if kind == "same" and (seq < st.next_seq or seq in st.held):
            if run is None and t_ns > st.max_t_ns and seq not in st.held:
                self._new_run(st, seq, run, now)  # no run ids: seq went back while time went on
                outcome = "restart"
            else:
                return self._late_or_stale(st, st.gaps, seq)
        elif kind == "same" and seq - st.next_seq > self.max_jump:
            c = st.jump
            if c is None or not (c[0] < seq <= c[0] + self.max_held and t_ns > c[1]):
                st.jump = (seq, t_ns)  # not believed yet: remembered, to be confirmed by the next one
                return "jump"
            self._resync(st, c[0], now)
            outcome = "resync"
        self.dirty.add(source)
        st.max_t_ns = max(st.max_t_ns, t_ns)
        st.held[seq] = (now, msg)
        if self._drain(st):
            st.progress_at = now
            if outcome == "held":
                outcome = "released" if seq not in st.held else "held"
        self._check_limits(st, now)
        return outcome

    def end(self, source: str, run: int | None, frames: int, t_ns: int, now: float) -> str:
        """The run ``run`` of ``source`` had ``frames`` frames (seq ``0 .. frames - 1``).

        Seqs still missing when the timeout has passed after this notice (and after every held
        point) are counted as dropped; held points at or beyond ``frames`` are stale.

        Returns
        -------
        str
            ``"ended"``; or, refused and changing nothing, ``"other_run"`` (not the run in
            progress of the source: an older run's, one never seen, or a forgery) or
            ``"bad_frames"`` (fewer frames than already released, or more than ``max_jump`` beyond
            the highest seq seen).
        """
        st = self._src.get(source)
        if st is None or run != st.run or (run is None and t_ns <= st.floor_t_ns):
            return "other_run"
        if not st.next_seq <= frames <= st.horizon() + self.max_jump:
            return "bad_frames"
        self.dirty.add(source)
        st.max_t_ns = max(st.max_t_ns, t_ns)
        st.end_seq, st.end_at = frames, now
        beyond = [s for s in st.held if s >= frames]
        for s in beyond:  # points the publisher says it never sent: not released
            del st.held[s]
        self.stale += len(beyond)
        self._check_limits(st, now)
        return "ended"

    def _late_or_stale(self, st: SourceState, gaps: Gaps | None, seq: int) -> str:
        if gaps is not None and gaps.take(seq):
            self.late += 1
            self.dirty.add(st.source)
            return "late"
        self.stale += 1
        return "stale"

    def awaited(self) -> int:
        """Frames announced by an end-of-run notice that have neither arrived nor been given up."""
        return sum(max(s.end_seq - s.next_seq - len(s.held), 0) for s in self._src.values() if s.end_seq is not None)

    def poll(self, now: float) -> None:
        """Give up gaps that have waited longer than the timeout."""
        for st in self._src.values():
            self._check_limits(st, now)

    def held(self) -> int:
        return sum(len(s.held) for s in self._src.values())

    # ------------------------------------------------------------------------------------------
    # persistence
    def sources(self) -> dict[str, SourceState]:
        """The state of every source (live objects: read them, do not change them)."""
        return self._src

    def restore(self, source: str, state: SourceState, now: float) -> None:
        """Put back ``source``'s state as persisted; held points, the end notice and the
        stuck-timer count from ``now`` (a restarted consumer gives late points a full timeout)."""
        state.held = {s: (now, m) for s, (_, m) in state.held.items()}
        state.progress_at = now
        if state.end_seq is not None:
            state.end_at = now
        state.jump = None
        state.source = source
        self._src[source] = state

    # ------------------------------------------------------------------------------------------
    def _run_state(self, source: str, seq: int, run: int | None, t_ns: int, now: float) -> tuple[SourceState, str]:
        """The source's state for a message of run ``run`` triggered at ``t_ns``, and whether it
        is ``"new"`` (first of the source), a ``"restart"`` (a new run: the old one is finished),
        the ``"same"`` run or an ``"older"`` one."""
        st = self._src.get(source)
        if st is None:
            # a run's seq starts at 0: what came before the first arrival was lost (unless we
            # joined long after the start)
            st = self._src[source] = SourceState(next_seq=0 if seq <= self.max_held else seq, run=run,
                                                 progress_at=now, source=source)
            return st, "new"
        if run is not None and st.run is not None and run != st.run:
            if t_ns <= st.max_t_ns:  # a message of an earlier run, late
                return st, "older"
            self._new_run(st, seq, run, now)
            return st, "restart"
        if run is None and t_ns <= st.floor_t_ns:
            return st, "older"
        return st, "same"

    def _new_run(self, st: SourceState, seq: int, run: int | None, now: float) -> None:
        self._give_up(st, everything=True)  # finish the old run
        if st.end_seq is not None and st.next_seq < st.end_seq:  # its notice came: its lost tail is known
            self.dropped += st.end_seq - st.next_seq
            st.gaps.add(st.next_seq, st.end_seq)
        st.prev_run, st.prev_gaps, st.gaps = st.run, st.gaps, Gaps()
        st.floor_t_ns = st.max_t_ns
        st.next_seq = 0 if seq <= self.max_held else seq
        st.run = run
        st.end_seq = None
        st.jump = None
        st.progress_at = now
        self.restarts += 1

    def _resync(self, st: SourceState, seq: int, now: float) -> None:
        """A confirmed jump: finish what is held, count the gap up to ``seq`` (the first refused
        point's slot, which is itself a gap: that point was not kept) and wait from there."""
        self._give_up(st, everything=True)
        self.dropped += seq - st.next_seq
        st.gaps.add(st.next_seq, seq)
        st.next_seq = seq
        st.jump = None
        st.progress_at = now
        self.resyncs += 1

    def _drain(self, st: SourceState) -> bool:
        released = False
        while st.next_seq in st.held:
            _, msg = st.held.pop(st.next_seq)
            st.next_seq += 1
            self._release(msg)
            released = True
        return released

    def _check_limits(self, st: SourceState, now: float) -> None:
        while st.held and (len(st.held) > self.max_held
                           or now - max(st.progress_at, min(t for t, _ in st.held.values())) > self.timeout_s):
            self._give_up(st)
            self.dirty.add(st.source)
        if (st.end_seq is not None and not st.held and st.next_seq < st.end_seq
                and now - st.end_at > self.timeout_s):
            self.dropped += st.end_seq - st.next_seq  # the tail of the run never came
            st.gaps.add(st.next_seq, st.end_seq)
            st.next_seq = st.end_seq
            self.dirty.add(st.source)

    def _give_up(self, st: SourceState, everything: bool = False) -> None:
        """Count the gap before the lowest held seq as dropped and release what follows it."""
        while st.held:
            first = min(st.held)
            self.dropped += first - st.next_seq
            st.gaps.add(st.next_seq, first)
            st.next_seq = first
            self._drain(st)
            if not everything:
                break


class GapCounter:
    """Frames missing from a stream that should be ``seq``, ``seq + 1``, ... per source (subscribers)."""

    def __init__(self) -> None:
        self._next: dict[str, int] = {}
        self.dropped = 0
        self.received = 0

    def see(self, source: str, seq: int) -> int:
        """Record one frame; returns how many frames were missing just before it."""
        self.received += 1
        nxt = self._next.get(source)
        gap = seq - nxt if nxt is not None and seq > nxt else 0
        self.dropped += gap
        self._next[source] = seq + 1  # a seq that goes back (publisher restart) re-syncs
        return gap
