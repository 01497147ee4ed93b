"""The API's durable store: one SQLite file (standard library ``sqlite3``), WAL, no waveforms.

What is kept, so that an API restarted (cleanly or killed) goes on where it stopped:

* every served point (``points``), the newest per source (``latest``, kept even when retention
  has deleted the source's history), the counters (``counters``);
* the reorderer's per-source state (``sources``: next seq, run, latest trigger time, end-of-run
  frame count) and the points it held for reordering (``held``).

Schema (version 1, ``PRAGMA user_version``)::

    points   (id INTEGER PRIMARY KEY AUTOINCREMENT,   -- release order
              source TEXT, segment INTEGER,           -- segment: the source's n-th run as released
              seq INTEGER, run INTEGER NULL, t_ns INTEGER, status TEXT,
              served_ns INTEGER,                      -- wall clock when committed (retention by age)
              body BLOB)                              -- the served point, msgpack (ServedPoint)
        INDEX points_by_segment (source, segment, seq)
        INDEX points_by_segment_id (source, segment)      -- then id: SQLite appends the rowid
    segments (source, segment, run, last_id, max_seq; PRIMARY KEY (source, segment))
    latest   (source PRIMARY KEY, body)
    counters (name PRIMARY KEY, value INTEGER)
    sources  (source PRIMARY KEY, next_seq, run, max_t_ns, floor_t_ns, end_seq,
              gaps, prev_run, prev_gaps)                -- given-up seq ranges (msgpack), to tell late points
    held     (source, seq, body; PRIMARY KEY (source, seq))
    meta     (key PRIMARY KEY, value)                 -- heartbeat_ns: the write probe

Within one segment (one run of one source) points are released in strictly increasing ``seq``,
so ``seq`` order there is ``id`` order: ``/v1/points?since_seq=S&source=X&after=C`` is, per
segment of ``X`` with points beyond ``S`` and ``C``, one seek for the first seq beyond ``S``
and one ordered range of ids from there (:meth:`HistoryDB.points` merges the segments by ``id``,
reading only as many rows as it returns); without ``source`` and ``since_seq`` it is one range
of ids. No query scans the table.

Writes: :meth:`HistoryDB.write` is one transaction per receiver-loop iteration (the points it
released, the counters, the state of the sources that changed, the held points added and gone,
retention), on the receiver thread's connection. Readers (HTTP threads) have connections of their
own: in WAL mode they read the last committed state beside the writer, without waiting for it.

Durability: ``synchronous=NORMAL`` in WAL mode keeps every committed transaction through a crash
of the process (SIGKILL); a power cut or an OS crash may lose the last few (never corrupt the
file). What was received after the last commit is lost with the process: those frames are seq
gaps for the restarted API, counted as dropped.

Retention: the oldest points go, at most :data:`RETENTION_BATCH` per transaction, while there
are more than ``retention_points`` or (``retention_s`` > 0) they were served longer ago than
``retention_s``; the age is checked oldest first, so a point released late (held for reordering)
may outlive a slightly newer one by the reorder timeout.

One process per file: :class:`HistoryDB` takes an exclusive ``flock`` on ``<file>.lock`` (the
kernel drops it when the process dies, SIGKILL included).
"""

from __future__ import annotations

import fcntl
import heapq
import logging
import os
import itertools
import sqlite3
import threading
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional
from urllib.parse import quote

import msgspec

from .ordering import Gaps, SourceState
from .wire import ServedPoint

log = logging.getLogger("mtcw.history")

SCHEMA_VERSION = 1
#: Points deleted by retention per transaction at most: a lowered ``retention_points`` (or a long
#: pause of ``retention_s``) is caught up over several batches instead of one long lock.
RETENTION_BATCH = 5000
#: The value that means "keep nothing across restarts" (a private temporary file, removed on close).
MEMORY = ":memory:"
#: SQLite INTEGER is signed 64-bit: larger seq, t_ns or run cannot be stored.
INT64_MAX = 2**63 - 1

_SCHEMA = """
CREATE TABLE points (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    source TEXT NOT NULL,
    segment INTEGER NOT NULL,
    seq INTEGER NOT NULL,
    run INTEGER,
    t_ns INTEGER NOT NULL,
    status TEXT NOT NULL,
    served_ns INTEGER NOT NULL,
    body BLOB NOT NULL
);
CREATE INDEX points_by_segment ON points (source, segment, seq);
CREATE INDEX points_by_segment_id ON points (source, segment);
CREATE TABLE segments (
    source TEXT NOT NULL,
    segment INTEGER NOT NULL,
    run INTEGER,
    last_id INTEGER NOT NULL,
    max_seq INTEGER NOT NULL,
    PRIMARY KEY (source, segment)
) WITHOUT ROWID;
CREATE TABLE latest (source TEXT PRIMARY KEY, body BLOB NOT NULL) WITHOUT ROWID;
CREATE TABLE counters (name TEXT PRIMARY KEY, value INTEGER NOT NULL) WITHOUT ROWID;
CREATE TABLE sources (
    source TEXT PRIMARY KEY,
    next_seq INTEGER NOT NULL,
    run INTEGER,
    max_t_ns INTEGER NOT NULL,
    floor_t_ns INTEGER NOT NULL,
    end_seq INTEGER,
    gaps BLOB NOT NULL,
    prev_run INTEGER,
    prev_gaps BLOB
) WITHOUT ROWID;
CREATE TABLE held (
    source TEXT NOT NULL,
    seq INTEGER NOT NULL,
    body BLOB NOT NULL,
    PRIMARY KEY (source, seq)
) WITHOUT ROWID;
CREATE TABLE meta (key TEXT PRIMARY KEY, value) WITHOUT ROWID;
"""

_ENCODE = msgspec.msgpack.Encoder().encode
_DECODE = msgspec.msgpack.Decoder(ServedPoint).decode
_JSON = msgspec.json.Encoder().encode


def _gaps(blob: bytes) -> Gaps:
    """Given-up seq ranges as stored; an unreadable value is no ranges (late points then count as stale)."""
    try:
        return Gaps(msgspec.msgpack.decode(blob, type=list[tuple[int, int]]))
    except Exception as err:
        log.error("store: given-up seq ranges could not be read (%s); forgotten", err)
        return Gaps()


class StoreError(ValueError):
    """The store cannot be opened (the message names ``store_path``)."""


@dataclass
class Segment:
    """The run of a source that released points are filed under.

    Attributes
    ----------
    number : int
        The source's segment counter (a new one for each run, as released).
    run : int or None
        The run id of its points.
    last_seq : int
        The highest seq released in it.
    """

    number: int
    run: Optional[int]
    last_seq: int


@dataclass
class Restored:
    """What :meth:`HistoryDB.load` found.

    Attributes
    ----------
    counters : dict
        Counter name -> value.
    latest : dict
        Source -> its newest served point.
    sources : dict
        Source -> reorderer state, with its held points (arrival times to be reset by the caller).
    segments : dict
        Source -> its current :class:`Segment`.
    points : int
        Rows in ``points``.
    bad_rows : int
        Newest points (``latest``) that could not be decoded (skipped, logged).
    bad_held : int
        Points held for reordering that could not be decoded: never to be released (the caller
        takes them out of ``received``; their seqs become gaps, counted as dropped, so that the
        books still balance).
    """

    counters: dict[str, int] = field(default_factory=dict)
    latest: dict[str, ServedPoint] = field(default_factory=dict)
    sources: dict[str, SourceState] = field(default_factory=dict)
    segments: dict[str, Segment] = field(default_factory=dict)
    points: int = 0
    bad_rows: int = 0
    bad_held: int = 0


def _connect(uri: str) -> sqlite3.Connection:
    conn = sqlite3.connect(uri, uri=True, isolation_level=None, check_same_thread=False, timeout=10.0)
    conn.execute("PRAGMA busy_timeout = 10000")
    return conn


_memory_ids = itertools.count()


class HistoryDB:
    """The SQLite store of one API process.

    Parameters
    ----------
    path : str or Path
        The database file (its parent directories are created), or ``":memory:"`` for a private
        database in this process's memory (SQLite's ``memdb``: no file, no WAL, readers and the
        writer take turns; gone with its last connection: nothing survives a restart).
    retention_points : int
        Points kept at most.
    retention_s : float
        Points served longer ago than this (s) are deleted; 0 = no age limit.
    on_bad_row : callable(where), optional
        Called for each stored point that cannot be decoded (``"points"``, ``"latest"``,
        ``"held"``), e.g. to count it.

    Raises
    ------
    StoreError
        The file cannot be made or opened, or another process holds it.
    """

    def __init__(self, path: str | Path, retention_points: int, retention_s: float = 0.0,
                 on_bad_row: Optional[Callable[[str], None]] = None) -> None:
        self.retention_points = retention_points
        self.retention_s = retention_s
        self.on_bad_row = on_bad_row or (lambda where: None)
        self._lock_fd = -1
        if str(path) == MEMORY:
            self.path = Path(MEMORY)
            self.uri = f"file:/mtcw-api-{os.getpid()}-{next(_memory_ids)}?vfs=memdb"
            self.durable = False
        else:
            self.path = Path(path).expanduser().absolute()
            self.uri = f"file:{quote(str(self.path))}"
            self.durable = True
            self._lock()
        self._readers: list[sqlite3.Connection] = []
        self._local = threading.local()
        self._readers_lock = threading.Lock()
        try:
            self.conn = self._open_writer()
        except BaseException:
            self._release_lock()
            raise
        self.rows = self.conn.execute("SELECT count(*) FROM points").fetchone()[0]
        self._held: dict[str, set[int]] = {}  # what the held table holds, per source

    def _lock(self) -> None:
        """Parents made, and the exclusive lock on ``<file>.lock`` taken (our pid written in it)."""
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._lock_fd = os.open(f"{self.path}.lock", os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            raise StoreError(f"store_path: cannot create {self.path}: {err.strerror or err}") from None
        try:
            fcntl.flock(self._lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.pread(self._lock_fd, 32, 0).decode(errors="replace").strip() or "?"
            self._release_lock()
            raise StoreError(f"store_path: {self.path} is in use by another process (pid {holder}); one API per "
                             f"store") from None
        os.ftruncate(self._lock_fd, 0)
        os.pwrite(self._lock_fd, str(os.getpid()).encode(), 0)

    # ------------------------------------------------------------------------------------------
    def _open_writer(self) -> sqlite3.Connection:
        try:
            conn = self._schema(_connect(self.uri))
        except sqlite3.DatabaseError as err:
            if not self.durable or isinstance(err, sqlite3.OperationalError):  # locked, read-only, no space, ...
                raise StoreError(f"store_path: {self.path}: {err}") from None
            # not a database, or a damaged one: keep it aside for inspection and start afresh
            aside = self.path.with_name(f"{self.path.name}.corrupt-{int(time.time())}")
            log.error("store: %s cannot be used (%s: %s); moved to %s, starting an empty store", self.path,
                      type(err).__name__, err, aside)
            for suffix in ("", "-wal", "-shm"):
                p = Path(f"{self.path}{suffix}")
                if p.exists():
                    p.rename(f"{aside}{suffix}")
            try:
                conn = self._schema(_connect(self.uri))
            except sqlite3.Error as err2:
                raise StoreError(f"store_path: {self.path}: {err2}") from None
        return conn

    def _schema(self, conn: sqlite3.Connection) -> sqlite3.Connection:
        try:
            mode = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            if mode.lower() != "wal" and self.durable:
                raise StoreError(f"store_path: {self.path}: SQLite refused WAL mode (got {mode!r})")
            conn.execute("PRAGMA synchronous = NORMAL")
            version = conn.execute("PRAGMA user_version").fetchone()[0]
            if version > SCHEMA_VERSION:
                raise StoreError(f"store_path: {self.path} has schema version {version}, made by a newer mtcw "
                                 f"(this one reads {SCHEMA_VERSION})")
            if version == 0:
                conn.execute("BEGIN IMMEDIATE")
                if conn.execute("SELECT count(*) FROM sqlite_master WHERE type = 'table'").fetchone()[0]:
                    conn.execute("ROLLBACK")
                    raise StoreError(f"store_path: {self.path} is an SQLite file of something else (tables but "
                                     f"no mtcw schema version)")
                conn.executescript("BEGIN;" + _SCHEMA + f"PRAGMA user_version = {SCHEMA_VERSION}; COMMIT;")
            conn.execute("SELECT count(*) FROM points").fetchone()  # the file is readable
        except BaseException:
            conn.close()
            raise
        return conn

    # ------------------------------------------------------------------------------------------
    def load(self) -> Restored:
        """Everything a restarted API needs (one read transaction)."""
        out = Restored(points=self.rows)
        c = self.conn
        c.execute("BEGIN")
        try:
            out.counters = {n: int(v) for n, v in c.execute("SELECT name, value FROM counters")}
            for source, body in c.execute("SELECT source, body FROM latest"):
                p = self._decode(body, "latest", source)
                if p is None:
                    out.bad_rows += 1
                else:
                    out.latest[source] = p
            for source, nxt, run, max_t, floor_t, end, gaps, prev_run, prev_gaps in c.execute(
                    "SELECT source, next_seq, run, max_t_ns, floor_t_ns, end_seq, gaps, prev_run, prev_gaps "
                    "FROM sources"):
                out.sources[source] = SourceState(next_seq=nxt, run=run, max_t_ns=max_t, floor_t_ns=floor_t,
                                                  end_seq=end, source=source, gaps=_gaps(gaps), prev_run=prev_run,
                                                  prev_gaps=None if prev_gaps is None else _gaps(prev_gaps))
            for source, seq, body in c.execute("SELECT source, seq, body FROM held"):
                # every row is remembered as stored, so that the source's next write deletes the
                # ones not put back in the reorderer
                self._held.setdefault(source, set()).add(seq)
                p = self._decode(body, "held", f"{source} seq {seq}")
                st = out.sources.get(source)
                if p is None:
                    out.bad_held += 1
                elif st is not None:
                    st.held[seq] = (0.0, p)
            for source, seg, run, max_seq in c.execute(
                    "SELECT source, segment, run, max_seq FROM segments s WHERE segment = "
                    "(SELECT max(segment) FROM segments t WHERE t.source = s.source)"):
                out.segments[source] = Segment(seg, run, max_seq)
        finally:
            c.execute("COMMIT")
        return out

    def write(self, points: Iterable[tuple[int, ServedPoint]], counters: Mapping[str, int],
              sources: Mapping[str, SourceState], now_ns: int) -> int:
        """One transaction: ``points`` (segment number and point, in release order), the
        ``counters`` (absolute values), the state and held points of the ``sources`` that changed,
        the newest point of each source, then retention. Nothing is written unless it all is.

        Parameters
        ----------
        points : iterable of (int, ServedPoint)
        counters : mapping
            Counter name -> value (the current totals, not increments).
        sources : mapping
            Source -> its live reorderer state (read, not changed).
        now_ns : int
            Wall clock (Unix ns): ``served_ns`` of the points, the heartbeat, retention by age.

        Returns
        -------
        int
            Points deleted by retention.

        Raises
        ------
        sqlite3.Error, OverflowError
            The transaction is rolled back; the caller keeps its batch and tries again.
        """
        rows = [(p.source, int(seg), p.seq, p.run, p.t_ns, p.status, now_ns, _ENCODE(p)) for seg, p in points]
        held_now = {s: set(st.held) for s, st in sources.items()}
        c = self.conn
        c.execute("BEGIN IMMEDIATE")
        try:
            if rows:
                c.executemany("INSERT INTO points (source, segment, seq, run, t_ns, status, served_ns, body) "
                              "VALUES (?, ?, ?, ?, ?, ?, ?, ?)", rows)
                last = c.execute("SELECT last_insert_rowid()").fetchone()[0]
                first = last - len(rows) + 1
                segs: dict[tuple[str, int], tuple[Optional[int], int, int]] = {}
                latest: dict[str, bytes] = {}
                for i, r in enumerate(rows):
                    segs[(r[0], r[1])] = (r[3], first + i, r[2])
                    latest[r[0]] = r[7]
                c.executemany("INSERT INTO segments (source, segment, run, last_id, max_seq) VALUES (?, ?, ?, ?, ?) "
                              "ON CONFLICT (source, segment) DO UPDATE SET last_id = excluded.last_id, "
                              "max_seq = max(max_seq, excluded.max_seq)",
                              [(s, g, run, last_id, seq) for (s, g), (run, last_id, seq) in segs.items()])
                c.executemany("INSERT OR REPLACE INTO latest (source, body) VALUES (?, ?)", latest.items())
            if counters:
                c.executemany("INSERT OR REPLACE INTO counters (name, value) VALUES (?, ?)", counters.items())
            for s, st in sources.items():
                c.execute("INSERT OR REPLACE INTO sources (source, next_seq, run, max_t_ns, floor_t_ns, end_seq, "
                          "gaps, prev_run, prev_gaps) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                          (s, st.next_seq, st.run, st.max_t_ns, st.floor_t_ns, st.end_seq, _ENCODE(st.gaps.ranges()),
                           st.prev_run, None if st.prev_gaps is None else _ENCODE(st.prev_gaps.ranges())))
                had = self._held.get(s, set())
                gone, new = had - held_now[s], held_now[s] - had
                if gone:
                    c.executemany("DELETE FROM held WHERE source = ? AND seq = ?", [(s, q) for q in gone])
                if new:
                    c.executemany("INSERT OR REPLACE INTO held (source, seq, body) VALUES (?, ?, ?)",
                                  [(s, q, _ENCODE(st.held[q][1])) for q in new])
            c.execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('heartbeat_ns', ?)", (now_ns,))
            deleted = self._retain(c, self.rows + len(rows), now_ns)
            c.execute("COMMIT")
        except BaseException:
            if c.in_transaction:
                c.execute("ROLLBACK")
            raise
        self.rows += len(rows) - deleted
        self._held.update(held_now)
        return deleted

    def _retain(self, c: sqlite3.Connection, rows_now: int, now_ns: int) -> int:
        """Delete the oldest points beyond the limits, at most :data:`RETENTION_BATCH`; returns how many."""
        cut: Optional[int] = None
        excess = min(rows_now - self.retention_points, RETENTION_BATCH)
        if excess > 0:  # the id of the first point kept (there is one: retention_points >= 1)
            cut = c.execute("SELECT id FROM points ORDER BY id LIMIT 1 OFFSET ?", (excess,)).fetchone()[0]
        if self.retention_s > 0:
            oldest_ok = now_ns - int(self.retention_s * 1e9)
            age_cut = None
            for pid, served in c.execute("SELECT id, served_ns FROM points ORDER BY id LIMIT ?", (RETENTION_BATCH,)):
                if served >= oldest_ok:
                    age_cut = pid
                    break
                age_cut = pid + 1
            if age_cut is not None and (cut is None or age_cut > cut):
                cut = age_cut
        if cut is None:
            return 0
        deleted = c.execute("DELETE FROM points WHERE id < ?", (cut,)).rowcount
        if deleted:
            c.execute("DELETE FROM segments WHERE last_id < ?", (cut,))
        return deleted

    # ------------------------------------------------------------------------------------------
    def _reader(self) -> sqlite3.Connection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            conn = self._local.conn = _connect(self.uri)
            conn.execute("PRAGMA query_only = 1")
            with self._readers_lock:
                self._readers.append(conn)
        return conn

    def points(self, since_seq: int, limit: int, source: Optional[str] = None,
               after: int = 0) -> tuple[list[bytes], bool, Optional[int]]:
        """Served points with ``seq > since_seq`` (of ``source``, or of every source) released
        after the point whose id is ``after`` (a cursor from an earlier answer), oldest first
        (release order), as JSON documents.

        One read transaction on this thread's connection. Without ``source`` and ``since_seq``:
        one range of the table's own order (``id > after``). Otherwise, per segment (a run of a
        source) with a point beyond ``since_seq`` and ``after``: one seek in
        ``points_by_segment`` for the first seq beyond ``since_seq``, then an ordered range of
        ``points_by_segment_id`` from there (seq and id rise together in a segment); the
        segments are merged by ``id``, reading only as many rows as are returned. A stored point
        that cannot be decoded is skipped, logged and reported to ``on_bad_row``.

        Returns
        -------
        points : list of bytes
            At most ``limit`` JSON objects.
        more : bool
            Whether further points match.
        next : int or None
            The cursor after the last point returned (its id), to pass as ``after``; None when
            nothing was returned.
        """
        conn = self._reader()
        conn.execute("BEGIN")
        cursors: list[sqlite3.Cursor] = []
        try:
            if source is None and since_seq < 0:
                cursors.append(conn.execute("SELECT id, body FROM points WHERE id > ? ORDER BY id", (after,)))
            else:
                segs = conn.execute("SELECT source, segment FROM segments WHERE max_seq > ? AND last_id > ?"
                                    + ("" if source is None else " AND source = ?"),
                                    (since_seq, after) + (() if source is None else (source,))).fetchall()
                for s, g in segs:
                    first = conn.execute("SELECT id FROM points INDEXED BY points_by_segment WHERE source = ? AND "
                                         "segment = ? AND seq > ? ORDER BY seq LIMIT 1", (s, g, since_seq)).fetchone()
                    if first is None:
                        continue
                    # cursors step lazily: each reads only the rows the merge takes from it
                    cursors.append(conn.execute("SELECT id, body FROM points INDEXED BY points_by_segment_id WHERE "
                                                "source = ? AND segment = ? AND id >= ? ORDER BY id",
                                                (s, g, max(first[0], after + 1))))
            out: list[bytes] = []
            more = False
            last: Optional[int] = None
            for pid, body in heapq.merge(*cursors, key=lambda r: r[0]):
                p = self._decode(body, "points", f"id {pid}")
                if p is None:
                    continue
                try:
                    doc = _JSON(p)
                except Exception as err:  # never expected of a decoded point; never a 500 either
                    self._bad("points", f"id {pid}", err)
                    continue
                if len(out) == limit:
                    more = True
                    break
                out.append(doc)
                last = pid
        finally:
            for cur in cursors:
                cur.close()
            conn.execute("COMMIT")
        return out, more, last

    def _decode(self, body: bytes, where: str, what: str) -> Optional[ServedPoint]:
        try:
            return _DECODE(body)
        except Exception as err:
            self._bad(where, what, err)
            return None

    def _bad(self, where: str, what: str, err: Exception) -> None:
        log.error("store: a stored point could not be read (%s %s: %s: %s); skipped", where, what,
                  type(err).__name__, err)
        self.on_bad_row(where)

    # ------------------------------------------------------------------------------------------
    def close(self) -> None:
        """Close every connection (a clean close also checkpoints the WAL) and release the file."""
        with self._readers_lock:
            for r in self._readers:
                r.close()
            self._readers.clear()
        try:
            self.conn.close()
        finally:
            self._release_lock()

    def _release_lock(self) -> None:
        if self._lock_fd >= 0:
            os.close(self._lock_fd)
            self._lock_fd = -1
