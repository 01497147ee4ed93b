"""Put results back in ``seq`` order and count what never came (pure Python, no sockets).

Several workers finish frames out of order; the consumer releases them in ``seq`` order per
source. A missing ``seq`` is waited for up to a timeout (or until too many later points are
held), then counted as dropped. A point that arrives after its slot was given up, or a repeat,
is counted as stale and never released twice. A publisher restart starts a new run: the
message's ``run`` id changes (or, from a publisher that sends none, ``seq`` goes back while the
trigger time ``t_ns`` moves forward); a point of the previous run that arrives afterwards is
stale, not new. An end-of-run notice (:meth:`Reorderer.end`) tells how many frames the run had,
so that frames lost after the last one that arrived are counted as dropped as well.
"""

from __future__ import annotations

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


@dataclass
class _SourceState:
    next_seq: int
    run: int | None = None
    max_t_ns: int = 0
    floor_t_ns: int = -1  # without run ids: points triggered at or before this belong to an older run
    held: dict[int, tuple[float, Sequenced]] = field(default_factory=dict)  # seq -> (arrival time, message)
    end_seq: int | None = None  # the run's frame count, once its end-of-run notice came
    end_at: float = 0.0  # when that notice came


class Reorderer(Generic[M]):
    """Per-source reorder buffer of messages with ``source``, ``seq``, ``t_ns`` and ``run``.

    Parameters
    ----------
    release : callable(message)
        Called for every point, once, in ``seq`` order per source.
    timeout_s : float
        How long the oldest held point waits for a missing predecessor.
    max_held : int
        Points held per source before the gap is given up regardless of time.
    """

    def __init__(self, release: Callable[[M], None], timeout_s: float = 2.0, max_held: int = 256) -> None:
        self._release = release
        self.timeout_s = timeout_s
        self.max_held = max_held
        self._src: dict[str, _SourceState] = {}
        self.dropped = 0
        self.stale = 0
        self.restarts = 0

    def add(self, msg: M, now: float) -> str:
        """Offer one point; returns ``"held"``, ``"released"``, ``"stale"`` or ``"restart"``."""
        source, seq, t_ns, run = msg.source, int(msg.seq), int(msg.t_ns), msg.run
        st, kind = self._run_state(source, seq, run, t_ns)
        if st is None:
            self.stale += 1
            return "stale"
        outcome = "restart" if kind == "restart" else "held"
        if kind == "same" and (seq < st.next_seq or seq in st.held):
            if run is None and t_ns > st.max_t_ns and seq not in st.held:
                self._new_run(st, seq, run)  # no run ids: seq went back while time went on
                outcome = "restart"
            else:
                self.stale += 1
                return "stale"
        st.max_t_ns = max(st.max_t_ns, t_ns)
        st.held[seq] = (now, msg)
        if self._drain(st) and outcome == "held":
            outcome = "released" if seq not in st.held else "held"
        self._check_limits(st, now)
        return outcome

    def end(self, source: str, run: int | None, frames: int, t_ns: int, now: float) -> str:
        """The run ``run`` of ``source`` had ``frames`` frames (seq ``0 .. frames - 1``).

        Seqs still missing when the timeout has passed after this notice (and after every held
        point) are counted as dropped. Returns ``"ended"`` or ``"stale"`` (a notice of an older run).
        """
        st, _ = self._run_state(source, 0, run, t_ns)
        if st is None:
            return "stale"
        st.max_t_ns = max(st.max_t_ns, t_ns)
        st.end_seq, st.end_at = frames, now
        self._check_limits(st, now)
        return "ended"

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
    def _run_state(self, source: str, seq: int, run: int | None, t_ns: int) -> tuple[_SourceState | None, str]:
        """The source's state for a message of run ``run`` triggered at ``t_ns``, and whether it
        is ``"new"`` (first of the source), a ``"restart"`` (a new run: the old one is finished)
        or the ``"same"`` run; ``(None, "stale")`` for a message of an earlier run."""
        st = self._src.get(source)
        if st is None:
            # a run's seq starts at 0: what came before the first arrival was lost (unless we
            # joined long after the start)
            st = self._src[source] = _SourceState(next_seq=0 if seq <= self.max_held else seq, run=run)
            return st, "new"
        if run is not None and st.run is not None and run != st.run:
            if t_ns <= st.max_t_ns:  # a message of an earlier run, late
                return None, "stale"
            self._new_run(st, seq, run)
            return st, "restart"
        if run is None and t_ns <= st.floor_t_ns:
            return None, "stale"
        return st, "same"

    def _new_run(self, st: _SourceState, seq: int, run: int | None) -> None:
        self._give_up(st, everything=True)  # finish the old run
        st.floor_t_ns = st.max_t_ns
        st.next_seq = 0 if seq <= self.max_held else seq
        st.run = run
        st.end_seq = None
        self.restarts += 1

    def _drain(self, st: _SourceState) -> bool:
        released = False
        while st.next_seq in st.held:
            _, msg = st.held.pop(st.next_seq)
            st.next_seq += 1
            self._release(msg)
            released = True
        return released

    def _check_limits(self, st: _SourceState, now: float) -> None:
        while st.held and (len(st.held) > self.max_held
                           or now - min(t for t, _ in st.held.values()) > self.timeout_s):
            self._give_up(st)
        if (st.end_seq is not None and not st.held and st.next_seq < st.end_seq
                and now - st.end_at > self.timeout_s):
            self.dropped += st.end_seq - st.next_seq  # the tail of the run never came
            st.next_seq = st.end_seq

    def _give_up(self, st: _SourceState, everything: bool = False) -> None:
        """Count the gap before the lowest held seq as dropped and release what follows it."""
        while st.held:
            first = min(st.held)
            self.dropped += first - st.next_seq
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
