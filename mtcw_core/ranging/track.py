"""Range rate from the ranges of successive frames: a speed where the carrier's Doppler is lost,
and the direction of motion on one photodiode.

Issue 12, case 4: with a laser incoherent at the echo's delay (5.3 GHz linewidth, LO 9 m longer)
the LO x echo beat is no line, so one frame has no Doppler and its point says speed ``unknown``;
its range, from the self-beat or the squared record, is still good to a few mm. A target moving at
10 cm/s moves 1 cm between frames at 10 Hz: the ranges of a few frames carry its speed (the
dissertation's Table 3 reports ~10 cm/s there). On one photodiode the Doppler line gives |v| only;
the sign of the range rate is the direction the issue asks for.

**The estimate.** Each track holds the last ``frames`` unflagged points that joined it (time ``t_k``
from the frame's trigger stamp, range ``R_k`` unwrapped along the track, sigma ``s_k``); its range
rate is the weighted least-squares slope of ``R(t) = R0 + v*(t - tbar)`` over them, with variance
``1 / sum w_k (t_k - tbar)^2`` (``w_k = 1/s_k^2``). This is a constant-velocity Kalman filter
without process noise, run over a sliding window (a fixed-lag smoother): the window bounds how
long the constant-velocity assumption must hold, and the fit's residual chi-square tests it.

Honesty rules:

- only ``ok`` points without a flag (``near_edge``, ``cycle_ambiguous``, ``blended``) join a track:
  a flagged point may be on a wrong cycle; it gets no range rate;
- a point joins the track whose prediction it lies closest to, in sigmas, within ``gate_sigmas``
  (prediction variance from the fit plus the point's own); one point per track per frame;
  a point no track takes starts a new one;
- a track of one point takes a second within the fastest the point may move times the time
  between them (plus the gate): its speed where the chain measured one (``|v|`` + 5 sigma), 5 of
  its sigmas for a ``static`` claim, the search's largest speed where its speed is unknown, and no
  more than ``max_speed_mps`` where the bench declares one. For CW frames every step is wrapped into
  half the unambiguous range ``L``; where that allows a step of ``L/2``, the step's cycle is unknown
  (a target faster than ``L/(2*dt)`` aliases) and the point starts a track of its own instead: a
  laser incoherent at the target (speed unknown, up to tens of m/s) tracks only with
  ``max_speed_mps`` declared;
- where the chain measured the point's speed from its Doppler line (:attr:`TargetPoint.speed_measured`),
  the track's rate must agree with it within ``gate_sigmas`` (in |v| on one photodiode, signed
  for IQ); a rate that does not is withheld (:attr:`Tracker.disagree`);
- the rate is reported from ``min_frames`` points on (3: one degree of freedom for the test);
  its sigma is scaled by the residuals' Birge ratio when that exceeds 1 (the points' sigmas too
  small, or a small acceleration), and a window whose chi-square has a probability below
  ``chi2_p`` under constant velocity restarts from its newest point (a manoeuvre, or a point that
  was a different target);
- a track not seen for ``max_gap_s`` ends; a change of run, tone plan (unambiguous range) or a
  time stamp that does not advance ends every track of the source (time is the frames' trigger
  stamps ``t_ns``: a recording without them, every stamp equal, tracks nothing, each frame's end
  counted as ``time``); at most ``max_tracks`` per source (the longest unseen ends first).

What the tracker does not do: it leaves the chain's own speed (``velocity_mps``, from one frame's
Doppler) as it is, and adds ``track_id``, ``track_frames``, ``range_rate_mps`` and
``range_rate_sigma_mps`` to the points it takes (:class:`~mtcw_core.results.TargetPoint`); positive
range rate is receding, the sign convention of ``velocity_mps``.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.stats import chi2 as chi2_dist

from ..results import FrameResult, TargetPoint

#: the largest window a track's rate may rest on
MAX_FRAMES = 64


class TrackSettings(BaseModel):
    """How points are followed over frames (kept apart from the chain's settings).

    ``frames``: the window, the most points a track's rate rests on. ``min_frames``: points before
    a rate is reported. ``max_speed_mps``: the fastest range rate a target may have (a track's
    second point must lie within it). ``gate_sigmas``: how far from a track's prediction a point
    may join it. ``chi2_p``: a window less likely than this under constant velocity restarts.
    ``max_gap_s``: a track unseen this long ends. ``max_tracks``: tracks per source.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    frames: int = Field(12, ge=3, le=MAX_FRAMES, description="the most points a track's rate rests on")
    min_frames: int = Field(3, ge=3, le=MAX_FRAMES, description="points before a rate is reported")
    max_speed_mps: float | None = Field(None, gt=0, description="the fastest range rate a target may have (m/s; "
                                        "default: each point's own bound, from its Doppler or the search)")
    gate_sigmas: float = Field(5.0, gt=0, le=100, description="sigmas from its prediction a point may join a track")
    chi2_p: float = Field(1e-4, gt=0, lt=0.5, description="a window less likely than this restarts")
    max_gap_s: float = Field(5.0, gt=0, description="a track unseen this long ends (s)")
    max_tracks: int = Field(8, ge=1, le=64, description="tracks per source")

    @model_validator(mode="after")
    def _window_holds_min_frames(self) -> "TrackSettings":
        if self.min_frames > self.frames:
            raise ValueError(f"min_frames: {self.min_frames} is more than the window holds (frames = {self.frames})")
        return self


@dataclass
class _Track:
    """One track: its window of (time s, unwrapped range m, sigma m), newest last."""

    id: int
    points: deque = field(default_factory=deque)

    @property
    def last_t(self) -> float:
        return self.points[-1][0]

    def fit(self) -> tuple[float, float, float, float, float, float] | None:
        """Weighted line through the window: (tbar s, range at tbar m, its variance m^2, rate m/s,
        its variance (m/s)^2, chi2 of the residuals); None below two points or times all equal."""
        if len(self.points) < 2:
            return None
        t, r, s = (np.array(c, dtype=np.float64) for c in zip(*self.points))
        w = 1.0 / s**2
        tbar = float(np.sum(w * t) / np.sum(w))
        dt = t - tbar
        sxx = float(np.sum(w * dt**2))
        if not sxx > 0:
            return None
        rbar = float(np.sum(w * r) / np.sum(w))
        rate = float(np.sum(w * dt * (r - rbar)) / sxx)
        chi2 = float(np.sum(w * (r - rbar - rate * dt) ** 2))
        return tbar, rbar, 1.0 / float(np.sum(w)), rate, 1.0 / sxx, chi2

    def predict(self, t: float) -> tuple[float, float, float | None]:
        """(range m, its variance m^2, None) at time ``t`` from the fit with two points or more;
        with one, (its range, its variance, the time since it s): the step's reach is then the
        joining point's speed bound times that time."""
        f = self.fit()
        t0, r0, s0 = self.points[-1]
        if f is None:
            return r0, s0**2, abs(t - t0)
        tbar, rbar, var_r, rate, var_rate, _ = f
        return rbar + rate * (t - tbar), var_r + (t - tbar) ** 2 * var_rate, None


class Tracker:
    """Points of successive frames of each source followed as tracks (module docstring).

    ``update`` takes the chain's results in time order (one source's frames as one worker sees
    them: a share is enough, the time stamps say how far apart they are) and returns each with its
    unflagged ``ok`` points carrying ``track_id``/``track_frames`` and, from ``min_frames`` on,
    ``range_rate_mps``/``range_rate_sigma_mps``. It never raises on a result.

    Attributes
    ----------
    ends : dict
        Tracks ended, by reason (``gap``, ``run``, ``plan``, ``time``, ``full``), for the operator.
    restarts : int
        Windows restarted from their newest point (chi-square below ``chi2_p``).
    disagree : int
        Rates withheld because the chain's own Doppler speed of the point says otherwise.
    ambiguous : int
        Steps not taken because their cycle was unknown (a one-point track, a speed bound allowing
        half the unambiguous range: declare ``max_speed_mps``).
    """

    def __init__(self, settings: TrackSettings | None = None, max_sources: int = 64) -> None:
        self.settings = settings or TrackSettings()
        self.max_sources = max_sources
        self._sources: dict[str, _SourceTracks] = {}
        self.ends: dict[str, int] = {}
        self.restarts = self.disagree = self.ambiguous = 0

    def update(self, res: FrameResult, run: int | None = None) -> FrameResult:
        """``res`` with its points annotated (a new result; ``res`` itself is not changed)."""
        src = self._sources.get(res.source)
        if src is None:
            if len(self._sources) >= self.max_sources:  # bounded memory: forget the others
                for s in self._sources.values():
                    self._end(s, list(s.tracks), "full")
                self._sources.clear()
            src = self._sources[res.source] = _SourceTracks()
        t = res.t_ns * 1e-9
        period = res.unambiguous_range_m if res.coarse_range_m is None else None
        why = ("run" if run != src.run else "plan" if period != src.period
               else "time" if src.last_t is not None and t <= src.last_t else None)
        if why and src.tracks:
            self._end(src, list(src.tracks), why)
        src.run, src.period, src.last_t = run, period, t
        self._end(src, [k for k in src.tracks if t - k.last_t > self.settings.max_gap_s], "gap")
        if res.status != "ok":
            return res
        targets = list(res.targets)
        for i, k, r in self._associate(src, targets, t):
            targets[i] = self._join(src, k, targets[i], t, r)
        return replace(res, targets=targets)

    # ---------------------------------------------------------------------------------------
    def _associate(self, src: "_SourceTracks", points: list[TargetPoint], t: float):
        """(point index, track or None, its range unwrapped along that track m) for every point that
        may join: nearest in sigmas first, one point per track; None starts a track."""
        st = self.settings
        usable = [i for i, p in enumerate(points)
                  if not p.flagged and math.isfinite(p.range_m) and p.range_sigma_m > 0 and math.isfinite(p.range_sigma_m)]
        preds = [(k, *k.predict(t)) for k in src.tracks]  # one fit per track
        pairs = []
        for i in usable:
            p = points[i]
            for k, r_pred, var, dt_one in preds:
                step = _wrap(p.range_m - r_pred, src.period)
                sd = math.sqrt(var + p.range_sigma_m**2)
                reach = 0.0 if dt_one is None else self._speed_bound(p) * dt_one
                bound = reach + st.gate_sigmas * sd
                if reach > 0 and src.period is not None and bound >= src.period / 2:
                    self.ambiguous += 1  # a step of half the unambiguous range: which cycle it took is unknown
                    continue
                if abs(step) <= bound:  # fitted tracks first (|step| <= gate sigmas), then one-point tracks
                    pairs.append((abs(step) / sd + (st.gate_sigmas if reach > 0 else 0.0), i, k, r_pred + step))
        pairs.sort(key=lambda q: q[0])
        taken_p, taken_k, out = set(), set(), []
        for _, i, k, r in pairs:
            if i not in taken_p and k.id not in taken_k:
                taken_p.add(i)
                taken_k.add(k.id)
                out.append((i, k, r))
        out += [(i, None, points[i].range_m) for i in usable if i not in taken_p]
        return out

    def _speed_bound(self, p: TargetPoint) -> float:
        """The fastest point ``p`` may move (m/s): its measured speed plus ``gate_sigmas`` of its sigma,
        ``gate_sigmas`` sigmas of a ``static`` claim, the search's largest speed (its sigma) where its
        speed is unknown; no more than a declared ``max_speed_mps``."""
        st = self.settings
        if p.speed_measured:
            v = abs(p.velocity_mps) + st.gate_sigmas * p.velocity_sigma_mps
        elif p.direction == "static":
            v = st.gate_sigmas * p.velocity_sigma_mps
        else:
            v = p.velocity_sigma_mps
        return min(v, st.max_speed_mps) if st.max_speed_mps else v

    def _join(self, src: "_SourceTracks", k: _Track | None, p: TargetPoint, t: float, r: float) -> TargetPoint:
        """Point ``p`` at range ``r`` (m, unwrapped along ``k``) joins track ``k`` (None: a new one)."""
        st = self.settings
        if k is None:
            if len(src.tracks) >= st.max_tracks:
                self._end(src, [min(src.tracks, key=lambda q: q.last_t)], "full")
            k = _Track(src.next_id)
            src.next_id += 1
            src.tracks.append(k)
        k.points.append((t, r, p.range_sigma_m))
        while len(k.points) > st.frames:
            k.points.popleft()
        f = k.fit()
        if f is not None and len(k.points) >= 3 and chi2_dist.sf(f[5], len(k.points) - 2) < st.chi2_p:
            self.restarts += 1
            while len(k.points) > 1:  # the window restarts from its newest point
                k.points.popleft()
            f = None
        n = len(k.points)
        if f is None or n < st.min_frames:
            return replace(p, track_id=k.id, track_frames=n)
        _, _, _, rate, var_rate, chi2 = f
        sigma = math.sqrt(var_rate * max(1.0, chi2 / (n - 2)))
        if p.speed_measured:  # the chain's Doppler speed: |v| on one photodiode, signed for IQ
            v = p.velocity_mps if p.direction in ("receding", "approaching") else None
            d = (rate - v) if v is not None else (abs(rate) - abs(p.velocity_mps))
            if abs(d) > st.gate_sigmas * math.hypot(sigma, p.velocity_sigma_mps):
                self.disagree += 1
                return replace(p, track_id=k.id, track_frames=n)
        return replace(p, track_id=k.id, track_frames=n, range_rate_mps=rate, range_rate_sigma_mps=sigma)

    def _end(self, src: "_SourceTracks", tracks: list[_Track], reason: str) -> None:
        for k in tracks:
            src.tracks.remove(k)
            self.ends[reason] = self.ends.get(reason, 0) + 1


@dataclass
class _SourceTracks:
    tracks: list[_Track] = field(default_factory=list)
    next_id: int = 1
    run: int | None = None
    period: float | None = None
    last_t: float | None = None


def _wrap(d: float, period: float | None) -> float:
    """``d`` wrapped into [-period/2, period/2) (unchanged without a period)."""
    if period is None or not period > 0:
        return d
    return (d + period / 2) % period - period / 2
