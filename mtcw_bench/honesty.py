"""The honesty map: does every number the chain reports come with a sigma that covers its error?

    mtcw bench --honesty [--quick] [-o docs/benchmarks/honesty]     (or mtcw-bench-honesty ...)

Issue 12's rule: a target is reported ``ok`` only with a sigma that covers its error; when the
chain cannot know, it flags, widens the sigma, or reports no target. This module measures that
rule over the operating envelope, one *cell* at a time (a scene, an echo loss, a profile), and
counts what breaks it.

The grid
--------
Not the full product of the issue's axes (that would be ~10^5 cells): *slices* through a base
configuration -- the bundled ``cw-bench`` plan (500/700/950 MHz, 1064 nm, 100 kHz linewidth,
single photodiode, shot + thermal noise, one target at 1.234 m, 2^16 samples at 5 GS/s) --
each varying one or two axes (:func:`grid`):

========== ================================================================ =========
slice      rows                                                             rungs
========== ================================================================ =========
length     record 2^16, 2^18, 2^20 x speed (5)                              9
receiver   balanced, iq x speed (5)                                         7
laser      ideal, 5.3 GHz at 500x L_coh, 100 kHz at 15 m x speed (5);       7
           5.3 GHz static at 2^18, 2^20; at 2^16-2^20 at 30-70 dB loss      (5)
targets    static + mover, two movers, three movers x (single 2^16, iq       7
           2^16, single 2^18)
six-tone   the 6-tone plan at 2^16, 2^18, 2^20 x speed (0, 40 bins,          9
           0.45 x spacing)
jitter     60 ps rms trigger jitter x (static, 1.62 m/s) x (2^16, 2^18)      7
quasi-cw   the bundled quasi-CW bench (1e6 samples), losses 40/55/65/75 dB   4
========== ================================================================ =========

Speeds: 0; half a record bin (``fs/N``); 6 bins; 1.62 m/s (40 bins at 2^16); 0.45 x the
smallest tone spacing (the largest Doppler the search allows is half of it). Speeds are
positive (receding), so an IQ receiver sees ``f_d < 0``.

Echo loss is a ladder of *rungs*, each the loss at which the bound's median line SNR (post
integration, from the truth: :func:`mtcw_core.evaluate.range_bound`) of the first target would
be 45, 30, 20, 13, 10, 5, 0 dB -- from strong to 10 dB past the chain's line threshold
(``min_line_snr_db`` = 10 dB); the ``length`` and ``six-tone`` slices use the losses of their
2^16 row at every record length (so that "more samples never lose a target" compares the same
target) and add rungs at -6 and -12 dB so that 2^20 also goes 10 dB past the threshold. Other
targets keep their loss offsets. The bound is computed for the first target alone (an IQ
receiver: its balanced twin; it is not defined for quasi-CW frames). A 5.3 GHz laser ranges
from the echo self-beat: its SNR is :func:`self_beat_snr_db` (the LO x echo beat spread over the
band counted as noise), the ladder found by bisection; rungs it cannot reach (its SNR saturates
near 25 dB at 0 dB loss, 2^16) are left out.

Every cell's frames are simulated once and processed by every profile (``fast``, ``balanced``,
``accurate``; ``seed`` on request: ~1 s a frame). The nine failures of issue 12, at the sizes
the issue gives, form one more slice, ``cases`` (:func:`case_scenes`). The full map (the
command above without ``--quick``): 73 rows, 471 (row, loss) groups, 16 frames each (the cases
4-16), 7472 simulated frames, 22416 processed, 30 min on 2 cores; the quick map: 9 rows at 2^16,
2 rungs, 3 frames, ~20 s.

Per cell (:func:`summarise`): range and speed z-scores (error over the point's own sigma: mean,
std, a robust std, largest ``|z|``), **confident-wrong frames** (status ok, a point answering a
truth with no flag raised and ``|z| > 5`` on range or speed -- issue 12's definition),
**confident-false frames** (an unflagged point that answers no truth: a ghost), flagged-wrong
points (a flag beside a wrong number), missed targets, false targets, flags raised, and the
issue's targets checked where they apply (:func:`check_targets`). Matching and z-scores:
:func:`mtcw_core.evaluate.judge_frame`. The ``crb`` target's reference is the white-noise bound
(``crb_range_m``); where it judges a cell and the laser has a linewidth, ``crb_pn_range_m`` is the
bound with the laser's phase-noise leakage between lines counted as noise
(:func:`crb_phase_noise`), which says which misses a phase-noise floor explains.
"""

from __future__ import annotations

import argparse
import collections
import functools
import math
import os
import statistics
import sys
import time
import zlib
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from mtcw_core.calibrate import tone_amplitudes
from mtcw_core.chain import get_profile, process_frame
from mtcw_core.dsp.tones import fit_lines
from mtcw_core.evaluate import Z_WRONG, FrameVerdict, judge_frame, phase_noise_bound, range_bound
from mtcw_core.phase import C
from mtcw_core.ranging.accumulate import AccumulateSettings, Accumulator, mean_truth
from mtcw_core.ranging.track import Tracker, TrackSettings
from mtcw_core.scene import Scene, load_scene, scene_from_dict, scene_variant
from mtcw_core.simulate import Simulator

#: Line SNR (dB) of the first target at each rung of the loss ladder; the chain's line threshold is 10 dB.
RUNGS_DB: tuple[float, ...] = (45.0, 30.0, 20.0, 13.0, 10.0, 5.0, 0.0)
#: Extra rungs for slices whose losses are those of the 2^16 row at every record length.
LONG_RUNGS_DB: tuple[float, ...] = RUNGS_DB + (-6.0, -12.0)
QUICK_RUNGS_DB: tuple[float, ...] = (30.0, 10.0)
#: the 5.3 GHz static rows past the self-beat's ladder (which ends at ~26 dB): echo losses (dB)
#: toward the squared record's one-frame reach (issue 12's target: sigma <= 1 cm to >= 40 dB)
FAR_LOSSES_DB: tuple[float, ...] = (30.0, 40.0, 50.0, 60.0, 70.0)
PROFILES: tuple[str, ...] = ("fast", "balanced", "accurate")
#: line SNR (dB) above which a target must be found: the chain's 10 dB line threshold + 3 dB
MUST_FIND_SNR_DB = 13.0
#: issue 12's target on z-scores in every cell above the threshold
Z_MEAN_MAX, Z_STD_RANGE = 0.3, (0.8, 1.25)
JITTER_S = 60e-12


# -------------------------------------------------------------------------------------------
# scenes
def with_targets(scene: Scene, targets: list[dict]) -> Scene:
    """``scene`` with its target list replaced (``scene_variant`` merges lists item by item)."""
    data = scene.model_dump()
    data["targets"] = targets
    return scene_from_dict(data, origin=f"variant of {scene.name}")


def bin_speed_mps(scene: Scene, bins: float) -> float:
    """The radial speed (m/s) whose Doppler is ``bins`` record bins (``fs/N``) of ``scene``."""
    d = scene.digitizer
    return bins * d.sample_rate_hz / d.samples * scene.laser.wavelength_m / 2


def spacing_speed_mps(scene: Scene, fraction: float = 0.45) -> float:
    """The speed whose Doppler is ``fraction`` of the smallest tone spacing (m/s)."""
    t = sorted(scene.tones_hz)
    return fraction * min(b - a for a, b in zip(t, t[1:])) * scene.laser.wavelength_m / 2


def base_scene(samples: int = 2**16) -> Scene:
    """The map's base: ``cw-bench`` with one static target at 1.234 m, ``samples`` long."""
    sc = load_scene("cw-bench")
    return with_targets(scene_variant(sc, digitizer={"samples": samples}), [{"range_m": 1.234, "loss_db": 20.0}])


def _speeds(scene: Scene, quick: bool = False) -> list[tuple[str, float]]:
    """The speed axis for ``scene``: (label, m/s)."""
    ref = base_scene()
    out = [("v=0", 0.0), ("v=0.5 bin", bin_speed_mps(scene, 0.5)), ("v=6 bins", bin_speed_mps(scene, 6)),
           ("v=1.62 m/s", round(bin_speed_mps(ref, 40), 2)), ("v=0.45 spacing", spacing_speed_mps(scene))]
    return [out[0], out[3]] if quick else out


@dataclass(frozen=True)
class Config:
    """One row of the map: a scene whose echo losses step down a ladder.

    ``calibrate``: the scene whose bound maps loss to line SNR for the ladder (default: this one);
    ``self_beat``: the scene ranges from the echo self-beat (a laser incoherent at the LO delay):
    its line SNR is :func:`self_beat_snr_db` and falls 2 dB per dB of echo loss;
    ``rungs_db``: line SNRs of the ladder (dB), or ``fixed_losses_db`` (first target's loss, dB),
    or neither (the scene as it is: the failure cases).
    """

    slice: str
    label: str
    scene: Scene
    calibrate: Scene | None = None
    self_beat: bool = False
    rungs_db: tuple[float, ...] = ()
    fixed_losses_db: tuple[float, ...] = ()
    frames: int | None = None  # overrides the grid's frames per cell
    note: str = ""
    #: K > 0: also a cell of mtcw_core.ranging.accumulate's points over K frames (profile "balanced+accK")
    accumulate: int = 0
    #: K > 0: also a cell of ``balanced``'s points with their range rate over K frames
    #: (mtcw_core.ranging.track, profile "balanced+trkK"): the range rate's z counts as a speed's
    track: int = 0

    @property
    def key(self) -> str:
        return f"{self.slice}/{self.label}"

    @property
    def slope(self) -> float:
        """dB of line SNR lost per dB of echo loss: the LO beats scale with the echo's field, the
        self-beat with its power."""
        return 2.0 if self.self_beat else 1.0


@dataclass(frozen=True)
class Group:
    """The unit of work: one config at one rung; its frames are simulated once for every profile."""

    config: Config
    rung: str  # "snr=13", "loss=55", "as is"
    snr_target_db: float | None
    scene: Scene
    frames: int
    seed: int

    @property
    def cost(self) -> float:
        """Rough relative cost (samples x frames) for scheduling the largest first."""
        return self.scene.digitizer.samples * self.frames


def _target(range_m: float, v: float, loss: float) -> dict:
    return {"range_m": range_m, "velocity_mps": v, "loss_db": loss}


def _lowcoh(scene: Scene) -> Scene:
    return scene_variant(scene, laser={"linewidth_hz": 5.3e9}, paths={"lo_path_difference_m": 9.0})


def grid(quick: bool = False, slices: list[str] | None = None) -> list[Config]:
    """The map's rows (see the module docstring). ``quick``: a few rows at 2^16, two rungs."""
    rungs = QUICK_RUNGS_DB if quick else RUNGS_DB
    long_rungs = QUICK_RUNGS_DB if quick else LONG_RUNGS_DB
    out: list[Config] = []
    b16 = base_scene()
    lengths = [2**16] if quick else [2**16, 2**18, 2**20]

    # length x speed: the losses of the 2^16 row at every length
    for lab, v in _speeds(b16, quick):
        cal = with_targets(b16, [_target(1.234, v, 20.0)])
        for n in lengths:
            sc = base_scene(n)
            scaled = lab in ("v=0.5 bin", "v=6 bins")  # speeds in bins of this record; the others in m/s
            vv = bin_speed_mps(sc, float(lab.split("=")[1].split()[0])) if scaled else v
            out.append(Config("length", f"N=2^{int(math.log2(n))} {lab}", with_targets(sc, [_target(1.234, vv, 20.0)]),
                              calibrate=cal, rungs_db=long_rungs))
    # receiver x speed
    for kind in ("balanced", "iq"):
        if quick and kind == "balanced":
            continue
        for lab, v in _speeds(b16, quick):
            sc = with_targets(scene_variant(b16, receiver={"kind": kind}), [_target(1.234, v, 20.0)])
            out.append(Config("receiver", f"{kind} {lab}", sc, rungs_db=rungs))
    # laser x speed: (name, laser, range m, loss dB); the base's 100 kHz laser at 15 m (echo delay
    # 100 ns, not 8): the phase difference over the delay moves a mover's Doppler ~12x more (found
    # by the envelope probe); only the 5.3 GHz rows in the quick map
    lasers = (("ideal", lambda s: scene_variant(s, laser={"linewidth_hz": 0.0}), 1.234, 20.0),
              ("100 kHz 15 m", lambda s: s, 15.0, 20.0), ("5.3 GHz", _lowcoh, 1.234, 5.0))
    for name, mk, range_m, loss in lasers:
        sb = name == "5.3 GHz"
        if quick and not sb:
            continue
        for lab, v in _speeds(b16, quick):
            sc = with_targets(mk(b16), [_target(range_m, v, loss)])
            out.append(Config("laser", f"{name} {lab}", sc, self_beat=sb, rungs_db=rungs))
        if sb and not quick:
            cal = with_targets(mk(b16), [_target(1.234, 0.0, 5.0)])
            for n in (2**18, 2**20):
                out.append(Config("laser", f"5.3 GHz N=2^{int(math.log2(n))} v=0", with_targets(mk(base_scene(n)),
                                  [_target(1.234, 0.0, 5.0)]), calibrate=cal, self_beat=True, rungs_db=rungs))
            # past the self-beat's ladder: the chain's square stage (the laser declared) to its reach
            for n in (2**16, 2**18, 2**20):
                out.append(Config("laser", f"5.3 GHz{'' if n == 2**16 else f' N=2^{int(math.log2(n))}'} v=0 far",
                                  with_targets(mk(base_scene(n)), [_target(1.234, 0.0, 5.0)]),
                                  fixed_losses_db=FAR_LOSSES_DB, note="beyond the self-beat: the squared record"))
    # several targets (speeds fixed in m/s: 40, 120, 250 bins at 2^16)
    v1, v2, v3 = (round(bin_speed_mps(b16, k), 2) for k in (40, 120, 250))
    sets = {"static+mover": [_target(0.81, 0.0, 20.0), _target(2.46, v1, 26.0)],
            "two movers": [_target(1.7, v1, 20.0), _target(3.9, v2, 23.0)],
            "three movers": [_target(1.7, v1, 20.0), _target(3.9, v2, 23.0), _target(5.3, v3, 26.0)]}
    variants = [("single 2^16", b16)] if quick else [("single 2^16", b16), ("iq 2^16", scene_variant(
        b16, receiver={"kind": "iq"})), ("single 2^18", base_scene(2**18))]
    for tname, tg in sets.items():
        if quick and tname != "static+mover":
            continue
        for vname, sc in variants:
            out.append(Config("targets", f"{tname} {vname}", with_targets(sc, tg), rungs_db=rungs))
    # the 6-tone plan
    six16 = scene_variant(load_scene("six-tone"), digitizer={"samples": 2**16})
    for lab, v in [s for s in _speeds(six16) if s[0] in ("v=0", "v=1.62 m/s", "v=0.45 spacing")][: 1 if quick else 3]:
        cal = with_targets(six16, [_target(7.89, v, 20.0)])
        for n in lengths:
            sc = with_targets(scene_variant(six16, digitizer={"samples": n}), [_target(7.89, v, 20.0)])
            out.append(Config("six-tone", f"N=2^{int(math.log2(n))} {lab}", sc, calibrate=cal, rungs_db=long_rungs))
    # known timing jitter the chain is not told of
    for n in lengths[:2]:
        for lab, v in (("v=0", 0.0), ("v=1.62 m/s", v1))[: 1 if quick else 2]:
            sc = with_targets(scene_variant(base_scene(n), noise={"trigger_jitter_s": JITTER_S}),
                              [_target(1.234, v, 20.0)])
            out.append(Config("jitter", f"60 ps N=2^{int(math.log2(n))} {lab}", sc, rungs_db=rungs))
            if quick:
                break
        if quick:
            break
    if not quick:
        out.append(Config("quasi-cw", "930 m, 1e6 samples", load_scene("quasi-cw-long-range"),
                          fixed_losses_db=(40.0, 55.0, 65.0, 75.0)))
    if slices:
        out = [c for c in out if c.slice in slices]
    return out


# -------------------------------------------------------------------------------------------
# the nine failures of issue 12, at the sizes the issue gives
def issue_scene(targets: list[dict], samples: int, tones=(500e6, 700e6, 950e6), **over) -> Scene:
    """Issue 12's set-up: 1064 nm, 100 kHz linewidth, shot + thermal noise, 5 GS/s; ``over`` as
    :func:`~mtcw_core.scene.scene_variant` takes it."""
    data = {"name": "issue-12", "laser": {"wavelength_m": 1.064e-6, "power_w": 0.05, "linewidth_hz": 100e3},
            "modulator": {"tones": [{"frequency_hz": f} for f in tones]}, "targets": targets,
            "noise": {"shot": True, "thermal": True}, "digitizer": {"sample_rate_hz": 5e9, "samples": samples}}
    sc = scene_from_dict(data)
    return scene_variant(sc, **over) if over else sc


SIX_TONES = (20e6, 500e6, 670e6, 700e6, 890e6, 950e6)
PE_TONES = (75e6, 500e6, 1900e6, 2450e6)


def case_scenes() -> dict[str, tuple[str, Scene, int]]:
    """Issue 12's failures as it states them: name -> (what it shows, scene, frames in the map)."""
    t1 = [_target(6.789, 0.21, 70.0)]
    low = load_scene("low-coherence")
    mt = load_scene("moving-target")
    return {
        "1 3-tone 70 dB": ("velocity bias at low SNR (3 tones, 2^18)", issue_scene(t1, 2**18), 16),
        "1 6-tone 70 dB": ("velocity bias at low SNR (6 tones, 2^18)", issue_scene(t1, 2**18, SIX_TONES), 16),
        "2 6-tone 1e6": ("more data loses the target (6 tones, 1e6)", issue_scene(t1, 1_000_000, SIX_TONES), 12),
        "3 static+mover": ("static beside a mover (1e6)", issue_scene(
            [_target(0.81, 0.0, 20.0), _target(2.46, 0.35, 26.0)], 1_000_000), 12),
        "4 low-coherence mover": ("5.3 GHz laser, mover at 10 cm/s (1e6)", with_targets(
            low, [_target(1.12, 0.10, 20.0)]), 12),
        "5 PE fast mover": ("50 m at 30 m/s, 75/500/1900/2450 MHz, 2^22 at 16.384 GS/s", issue_scene(
            [_target(50.0, 30.0, 20.0)], 2**22, PE_TONES, laser={"wavelength_m": 1e-6},
            digitizer={"sample_rate_hz": 16.384e9}), 4),
        "6 small Doppler": ("3.5 cm/s at 1550 nm, 10 kHz bins (45 kHz)", issue_scene(
            [_target(1.5, 0.035, 30.0)], 500_000, laser={"wavelength_m": 1.55e-6}), 12),
        "6 two small movers iq": ("20 and 65 kHz, 8/10 dB, coherent laser, IQ, 2^16 at 0.65536 GS/s (leakage between "
                                  "sub-guard movers)", _movers((2.0, 6.5), (8.0, 10.0), "iq"), 6),
        "6 two small movers 1 pd": ("the same at 40/42 dB on one photodiode (their cross-beat at 45 kHz)",
                                    _movers((2.0, 6.5), (40.0, 42.0), "single"), 6),
        # several movers beyond the guard, found by a probe of 599 such scenes (2026-11-26)
        "movers: pair 2 bins apart 1 pd": ("40 and 42 bins (10 kHz), 40/42 dB, one photodiode: one Doppler line for two",
                                           _movers((40.0, 42.0), (40.0, 42.0), "single"), 6),
        "movers: equal pair 1 bin apart iq": ("40 and 41 bins, 40/40 dB, IQ: the lines agree in phase, beat in amplitude",
                                              _movers((40.0, 41.0), (40.0, 40.0), "iq"), 6),
        "movers: strong echoes 1 pd": ("12 and 300 bins, 0/2 dB, one photodiode: their beat at 288 bins as strong as "
                                       "their own lines", _movers((12.0, 300.0), (0.0, 2.0), "single"), 6),
        "movers: beat before its parent 1 pd": ("12 and 40 bins, 10/12 dB, one photodiode: their beat at 28 bins",
                                                _movers((12.0, 40.0), (10.0, 12.0), "single"), 6),
        "movers: one at the sum of two 1 pd": ("40, 60 and 100 bins, 40/42/44 dB, one photodiode: 100 - 40 = 60",
                                               _movers((40.0, 60.0, 100.0), (40.0, 42.0, 44.0), "single"), 6),
        # found in the 2026-11-27 review: the echo's self-beat 10 dB above its own LO beats, at one range
        "3 echo above the LO 1 pd": ("moving-target at 0 dB loss (1e6): the self-beat stronger than the mover's "
                                     "Doppler lines", scene_variant(mt, targets=[{"loss_db": 0.0}],
                                                                    digitizer={"samples": 1_000_000}), 6),
        "7 timing jitter": ("60 ps trigger jitter (cw-bench, 1e6)", scene_variant(
            load_scene("cw-bench"), noise={"trigger_jitter_s": JITTER_S}), 12),
        "8 moving-target 60 dB": ("moving-target at 60 dB (sigma/CRB)", scene_variant(
            mt, targets=[{"loss_db": 60.0}]), 12),
        "8 moving-target 80 dB": ("moving-target at 80 dB (outliers)", scene_variant(
            mt, targets=[{"loss_db": 80.0}]), 12),
        "9 low-coherence 20 dB": ("beyond coherence, 20 dB", low, 8),
        "9 low-coherence 40 dB": ("beyond coherence, 40 dB", scene_variant(low, targets=[{"loss_db": 40.0}]), 8),
        "9 low-coherence 60 dB": ("beyond coherence, 60 dB", scene_variant(low, targets=[{"loss_db": 60.0}]), 8),
        "9 low-coherence 70 dB": ("beyond coherence, 70 dB (the square stage's one-frame reach)", scene_variant(
            low, targets=[{"loss_db": 70.0}]), 8),
    }


def _movers(bins: tuple[float, ...], losses_db: tuple[float, ...], receiver: str) -> Scene:
    """Movers ``bins`` record bins up (2^16 samples at 0.65536 GS/s, 1550 nm: 10 kHz, 7.75 mm/s a
    bin) at 1.5, 3.7 and 2.6 m, 150/200/270 MHz, a coherent laser (sharp lines: any leakage shows)."""
    bin_mps = 0.65536e9 / 2**16 * 1.55e-6 / 2
    ranges = (1.5, 3.7, 2.6)
    return issue_scene([_target(ranges[i], b * bin_mps, loss) for i, (b, loss) in enumerate(zip(bins, losses_db))],
                       2**16, (150e6, 200e6, 270e6), laser={"wavelength_m": 1.55e-6, "linewidth_hz": 0.0},
                       digitizer={"sample_rate_hz": 0.65536e9}, receiver={"kind": receiver})


def case_configs() -> list[Config]:
    return [Config("cases", name, sc, frames=n, note=what) for name, (what, sc, n) in case_scenes().items()] + \
        case9_accumulate_configs() + track_configs()


def track_label(k: int) -> str:
    """The profile name of a tracked cell: ``balanced``'s points, their range rate over K frames."""
    return f"balanced+trk{k}"


#: the window of the tracked cells, and their frames (the last 12 points of a cell rest on 12)
TRACK_FRAMES, TRACK_CELL_FRAMES = 12, 24
#: the largest speed the bench declares for its tracked rows (m/s): case 4's mover has no Doppler
#: line, and without a bound its steps' cycles would be unknown (mtcw_core.ranging.track)
TRACK_MAX_SPEED_MPS = 2.0


def track_configs() -> list[Config]:
    """Range rate over frames (:mod:`mtcw_core.ranging.track`): issue 12 case 4's mover (5.3 GHz laser:
    no Doppler line, speed unknown per frame), the coherent moving target on one photodiode (the
    rate's sign is its direction; its |v| from the Doppler line checks it) and two movers apart."""
    case4 = case_scenes()["4 low-coherence mover"][1]
    rows = (("4 low-coherence mover", case4, "case 4's mover (1e6): speed from the ranges of 12 frames"),
            ("moving-target 2^18", scene_variant(load_scene("moving-target"), digitizer={"samples": 2**18}),
             "one photodiode, 10 cm/s: the direction from the range rate"),
            ("two movers 1 pd", _movers((40.0, 120.0), (30.0, 33.0), "single"),
             "two movers at 0.31 and 0.93 m/s, one photodiode: one track each"))
    return [Config("cases", f"{name} trk{TRACK_FRAMES}", sc, frames=TRACK_CELL_FRAMES,
                   note=f"range rate over frames: {what}", track=TRACK_FRAMES) for name, sc, what in rows]


def accumulate_label(k: int) -> str:
    """The profile name of an accumulated cell: the chain's settings of ``balanced``, K frames."""
    return f"balanced+acc{k}"


def case9_accumulate_configs() -> list[Config]:
    """Case 9's reach (``docs/reach.md``): the low-coherence scene at 1e6 samples ranged from the
    whole band's digital IF mixing (:mod:`mtcw_core.ranging.accumulate`), one frame at 40 dB and
    32 frames at 60 and 85 dB (the issue's targets, and past them); 40 frames each, so that the
    last 9 points of a cell rest on 32 frames."""
    low = load_scene("low-coherence")
    rows = ((40.0, 1, 8), (60.0, 32, 40), (85.0, 32, 40))
    return [Config("cases", f"9 low-coherence {loss:g} dB acc{k}", scene_variant(low, targets=[{"loss_db": loss}]),
                   frames=n, note=f"beyond coherence, {loss:g} dB, whole-band IF mixing over {k} frame(s)",
                   accumulate=k) for loss, k, n in rows]


# -------------------------------------------------------------------------------------------
# the loss ladder
def bound_scene(scene: Scene) -> Scene | None:
    """The scene the bound is computed on: its first target alone; an IQ receiver's balanced twin.
    None for quasi-CW scenes (no bound defined)."""
    if scene.pulsing is not None:
        return None
    sc = with_targets(scene, [scene.targets[0].model_dump()])
    if sc.receiver.kind == "iq":
        sc = scene_variant(sc, receiver={"kind": "balanced"})
    return sc


def predicted_bound(scene: Scene, seed: int = 0):
    """:func:`mtcw_core.evaluate.range_bound` of :func:`bound_scene` (None where not defined)."""
    sc = bound_scene(scene)
    return None if sc is None else range_bound(sc, seed)


def self_beat_snr_db(scene: Scene, seed: int = 0) -> float | None:
    """Median post-integration SNR (dB) of the first target's echo self-beat lines at ``f_i``.

    The self-beat ``|E_echo|^2`` keeps the tone phases whatever the laser's coherence; for a
    laser incoherent at the LO delay it is all a single photodiode can range from. Its amplitude
    comes from a least-squares fit of a noiseless frame with an ideal laser and the target given
    a large speed (its LO beats then sit at ``f_i +- f_d``, fitted jointly and apart from ``f_i``).
    The noise is measured on a frame of the scene itself: the median periodogram level around the
    tones, which holds what the white-noise bound leaves out -- the LO x echo beat spread over the
    band by the laser's linewidth (it grows with the echo's field, so this SNR falls between 1 and
    2 dB per dB of loss). None for receivers that cancel the self-beat (balanced, IQ) and quasi-CW.
    """
    if scene.receiver.kind != "single" or scene.pulsing is not None:
        return None
    one = with_targets(scene, [scene.targets[0].model_dump()])
    n, fs = one.digitizer.samples, one.digitizer.sample_rate_hz
    t = np.asarray(one.tones_hz, float)
    x = Simulator(one, seed).frame(0).volts("pd")
    spec = np.abs(np.fft.rfft(x - np.mean(x))) ** 2
    f = np.fft.rfftfreq(n, 1 / fs)
    band = (f > 0.8 * t.min()) & (f < min(1.1 * t.max(), 0.499 * fs))
    s2 = float(np.median(spec[band])) / (n * math.log(2))  # E|X_k|^2 = N s2; median = ln2 * mean
    amp = self_beat_amplitude_v(one, seed)
    return float(np.median(10 * np.log10(n * amp**2 / (2 * s2))))


def self_beat_amplitude_v(scene: Scene, seed: int = 0) -> np.ndarray:
    """Amplitude (V) of the first target's self-beat line at each tone, shape (T,), tone order.

    A least-squares fit at ``f_i`` (jointly with the LO beats at ``f_i +- f_d``) of a noiseless
    frame of a single photodiode: an ideal laser, the LO path matched, the target moving at 0.3x
    the smallest tone spacing so that its LO beats leave ``f_i`` to the self-beat alone.
    """
    one = with_targets(scene, [scene.targets[0].model_dump()])
    t = np.asarray(one.tones_hz, float)
    v = spacing_speed_mps(one, 0.3)
    clean = scene_variant(one, laser={"linewidth_hz": 0.0}, paths={"lo_path_difference_m": 0.0},
                          receiver={"kind": "single"},
                          noise={"shot": False, "thermal": False, "rin_db_per_hz": None, "trigger_jitter_s": 0.0},
                          targets=[{"velocity_mps": v}], digitizer={"adc_bits": None})
    fr = Simulator(clean, seed).frame(0)
    fd = 2 * v / one.laser.wavelength_m
    return np.abs(fit_lines(fr.volts("pd"), np.concatenate([t, t + fd, t - fd]), fr.fs_hz))[: t.size]


def loss_shift_for(scene: Scene, snr_db: float, self_beat: bool) -> float:
    """The loss shift (dB, added to every target) that puts the first target's predicted line
    SNR at ``snr_db``: for LO beats 1 dB per dB, corrected twice by the bound at the shifted loss
    (at strong echoes the self-beat adds to a static target's lines); by bisection for the
    self-beat."""
    if not self_beat:
        shift = 0.0
        for _ in range(3):
            shift += predicted_snr_db(shifted(scene, shift), False) - snr_db
            shift = max(shift, -scene.targets[0].loss_db)
        return shift
    lo, hi = -scene.targets[0].loss_db, 150.0
    for _ in range(14):
        mid = 0.5 * (lo + hi)
        if predicted_snr_db(shifted(scene, mid), True) > snr_db:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def predicted_snr_db(scene: Scene, self_beat: bool, seed: int = 0) -> float | None:
    """The first target's predicted median line SNR (dB): the self-beat's, or the bound's."""
    if self_beat:
        return self_beat_snr_db(scene, seed)
    b = predicted_bound(scene, seed)
    return None if b is None else b.line_snr_db


def shifted(scene: Scene, shift_db: float) -> Scene:
    """``scene`` with every target's loss raised by ``shift_db`` (floored at 0 dB)."""
    return with_targets(scene, [{**t.model_dump(), "loss_db": max(0.0, t.loss_db + shift_db)} for t in scene.targets])


def _seed(key: str) -> int:
    return zlib.crc32(key.encode()) & 0x7FFFFFFF


def plan(configs: list[Config], frames: int) -> list[Group]:
    """Every (config, rung) group, with the loss shift that puts the first target at the rung's SNR."""
    cache: dict[tuple, float] = {}
    groups = []
    for c in configs:
        n = c.frames or frames
        if c.fixed_losses_db:
            for loss in c.fixed_losses_db:
                sc = with_targets(c.scene, [{**c.scene.targets[0].model_dump(), "loss_db": loss}]
                                  + [t.model_dump() for t in c.scene.targets[1:]])
                key = f"{c.key}@loss={loss:g}"
                groups.append(Group(c, f"loss={loss:g}", None, sc, n, _seed(key)))
            continue
        if not c.rungs_db:
            groups.append(Group(c, "as is", None, c.scene, n, _seed(c.key)))
            continue
        cal = c.calibrate or c.scene
        # the shift is relative to the calibrating scene's first-target loss
        ref_loss = cal.targets[0].loss_db - c.scene.targets[0].loss_db
        for r in c.rungs_db:
            ck = (cal.model_dump_json(), r, c.self_beat)
            if ck not in cache:
                cache[ck] = loss_shift_for(cal, r, c.self_beat)
            sc = shifted(c.scene, cache[ck] + ref_loss)
            if groups and groups[-1].config is c and groups[-1].scene == sc:
                continue  # a rung the echo cannot reach (the self-beat's SNR saturates at 0 dB loss)
            groups.append(Group(c, f"snr={r:g}", r, sc, n, _seed(f"{c.key}@snr={r:g}")))
    return groups


# -------------------------------------------------------------------------------------------
# one cell
def _stats(z: list[float]) -> dict:
    a = np.asarray(z, float)
    a = a[np.isfinite(a)]
    if a.size == 0:
        return {"n": 0, "mean": None, "std": None, "std_robust": None, "max_abs": None}
    return {"n": int(a.size), "mean": float(np.mean(a)), "std": float(np.std(a, ddof=1)) if a.size > 1 else None,
            "std_robust": float(1.4826 * np.median(np.abs(a - np.median(a)))) if a.size > 2 else None,
            "max_abs": float(np.max(np.abs(z)))}


def must_find(scene: Scene, first_snr_db: float | None, self_beat: bool, seed: int = 0) -> list[bool]:
    """Which of the scene's targets the chain must find: each target's own predicted median line
    SNR (the bound's, for that target alone; the first target's is ``first_snr_db``) at least
    :data:`MUST_FIND_SNR_DB`. Targets past the first keep their loss offsets, so a weaker second
    or third mover may lie below the threshold where the first is far above it; their self-beat
    SNR is not predicted (no requirement)."""
    out = []
    for j, t in enumerate(scene.targets):
        if j == 0:
            snr = first_snr_db
        elif self_beat:
            snr = None
        else:
            b = predicted_bound(with_targets(scene, [t.model_dump()]), seed)
            snr = None if b is None else b.line_snr_db
        out.append(snr is not None and snr >= MUST_FIND_SNR_DB)
    return out


def summarise(verdicts: list[FrameVerdict], n_truths: int, must: list[bool] | None = None) -> dict:
    """A cell's bookkeeping from its frames' verdicts (every profile's frames separately).

    Range z-statistics over every matched point (flagged or not); speed z mean/std over matched
    points that measured a speed (a ``static`` point's speed is a bound, not an estimate), the
    largest speed ``|z|`` over all matched points (a ``static`` claim far below the truth counts).
    ``*_z_unflagged_*``: the same over the unflagged points alone (a flag says the number may be
    wrong -- a cycle in doubt, a blend --, so only an unflagged point's sigma is a claim).
    ``missed_must_find``: the missed truths that ``must`` (:func:`must_find`, by truth index) says
    the chain had to find (all missed when ``must`` is None).
    """
    status: dict[str, int] = {}
    rz, sz_meas, sz_all, rz_clean, sz_clean, ratez = [], [], [], [], [], []
    for v in verdicts:
        status[v.status] = status.get(v.status, 0) + 1
        for p in v.points:
            if p.truth_index is None:
                continue
            if p.rate_z is not None:
                ratez.append(p.rate_z)
            rz.append(p.range_z)
            sz_all.append(p.speed_z)
            if p.speed_measured:
                sz_meas.append(p.speed_z)
            if not p.flagged:
                rz_clean.append(p.range_z)
                if p.speed_measured:
                    sz_clean.append(p.speed_z)
    r, s = _stats(rz), _stats(sz_meas)
    rc, sc, rt = _stats(rz_clean), _stats(sz_clean), _stats(ratez)
    sa = np.asarray(sz_all, float)
    return {
        "frames": len(verdicts), "ok": status.get("ok", 0), "no_target": status.get("no_target", 0),
        "rejected": status.get("rejected", 0),
        "points": sum(len(v.points) for v in verdicts),
        "truths": n_truths * len(verdicts),
        "missed": sum(len(v.missed) for v in verdicts),
        "missed_must_find": sum(1 for v in verdicts for j in v.missed if must is None or must[j]),
        "false_targets": sum(v.false_targets for v in verdicts),
        "flagged_points": sum(v.flagged_points for v in verdicts),
        "confident_wrong": sum(v.confident_wrong for v in verdicts),
        "confident_false": sum(v.confident_false for v in verdicts),
        "confident_any": sum(v.confident_wrong or v.confident_false for v in verdicts),
        "flagged_wrong": sum(v.flagged_wrong for v in verdicts),
        "range_z_n": r["n"], "range_z_mean": r["mean"], "range_z_std": r["std"], "range_z_std_robust": r["std_robust"],
        "range_z_max": r["max_abs"],
        "speed_z_n": s["n"], "speed_z_mean": s["mean"], "speed_z_std": s["std"], "speed_z_std_robust": s["std_robust"],
        "speed_z_max": float(np.max(np.abs(sa))) if sa.size else None,
        "range_z_unflagged_n": rc["n"], "range_z_unflagged_mean": rc["mean"], "range_z_unflagged_std": rc["std"],
        "speed_z_unflagged_n": sc["n"], "speed_z_unflagged_mean": sc["mean"], "speed_z_unflagged_std": sc["std"],
        "rate_z_n": rt["n"], "rate_z_mean": rt["mean"], "rate_z_std": rt["std"], "rate_z_max": rt["max_abs"],
    }


def z_in_band(mean: float, std: float) -> bool:
    """A cell's z values meet issue 12's target: ``|mean| < Z_MEAN_MAX``, std within ``Z_STD_RANGE``."""
    return abs(mean) < Z_MEAN_MAX and Z_STD_RANGE[0] <= std <= Z_STD_RANGE[1]


def check_targets(cell: dict) -> list[str]:
    """Issue 12's targets this cell misses: ``confident_wrong``, ``confident_false``, ``missed``
    (a target whose own predicted line SNR is >= 13 dB not found in every frame: ``missed_must_find``), ``range_z``/``speed_z``
    (|mean| >= 0.3 or std outside 0.8-1.25, above 13 dB with >= 5 z-values), ``crb`` (balanced
    range std > 1.3x the bound on a first target that moves, 40-80 dB)."""
    miss = []
    if cell["confident_wrong"]:
        miss.append("confident_wrong")
    if cell["confident_false"]:
        miss.append("confident_false")
    above = cell.get("predicted_snr_db") is not None and cell["predicted_snr_db"] >= MUST_FIND_SNR_DB
    if cell.get("missed_must_find", cell["missed"] if above else 0):
        miss.append("missed")
    if above:
        for k in ("range_z", "speed_z"):
            n, m, s = cell[f"{k}_n"], cell[f"{k}_mean"], cell[f"{k}_std"]
            if n >= 5 and s is not None and not z_in_band(m, s):
                miss.append(k)
    r = cell.get("range_std_over_crb")
    if (cell["profile"] == "balanced" and r is not None and cell.get("first_moves")
            and 40 <= cell["loss_db"][0] <= 80 and r > 1.3):
        miss.append("crb")
    return miss


#: noiseless frames (and their ideal-laser twins) behind a cell's phase-noise bound
PN_BOUND_FRAMES = 8


def in_crb_domain(scene: Scene) -> bool:
    """Whether the ``crb`` target judges cells of ``scene``: a first target that moves, 40-80 dB."""
    return scene.targets[0].velocity_mps != 0 and 40 <= scene.targets[0].loss_db <= 80


def crb_phase_noise(g: Group, bound) -> float | None:
    """The range bound of the group's first target with the laser's phase-noise leakage counted
    as noise (:func:`mtcw_core.evaluate.phase_noise_bound`), m: where the ``crb`` target judges
    the cells and the laser has a linewidth (it equals the white-noise bound for an ideal laser);
    else None. It says which misses of the white-noise bound a phase-noise floor explains; the
    target itself stays on the white-noise bound."""
    if bound is None or g.scene.laser.linewidth_hz <= 0 or not in_crb_domain(g.scene):
        return None
    b = phase_noise_bound(bound_scene(g.scene), g.seed, PN_BOUND_FRAMES)
    return None if b is None else b.range_sigma_m


def _first_target_efficiency(verdicts: list[FrameVerdict], lam_min: float) -> float | None:
    """Sample std (m) of the first truth's range errors, wrong cycles (> lam_min/4) left out."""
    e = [p.range_error_m for v in verdicts for p in v.points
         if p.truth_index == 0 and abs(p.range_error_m) <= lam_min / 4]
    return float(np.std(e, ddof=1)) if len(e) >= 3 else None


def tally(counts: collections.Counter, v: FrameVerdict, tag: str | None = None) -> bool:
    """Count one judged frame in ``counts`` (the probes' books): ``frames``, ``cw`` (confident
    wrong), ``cf`` (confident false), ``missed`` (truths no point answers), ``flagged`` (flagged
    points) and ``flagged_right`` (flagged points answering a truth within ``Z_WRONG``: what a
    flag cost), keyed ``(tag, name)`` when a tag is given; whether the frame was confidently
    wrong or false."""
    key = (lambda name: (tag, name)) if tag is not None else (lambda name: name)
    counts[key("frames")] += 1
    counts[key("cw")] += int(v.confident_wrong)
    counts[key("cf")] += int(v.confident_false)
    counts[key("missed")] += len(v.missed)
    counts[key("flagged")] += v.flagged_points
    counts[key("flagged_right")] += sum(p.flagged and p.truth_index is not None and not p.wrong(v.z_wrong)
                                        for p in v.points)
    return v.confident_wrong or v.confident_false


def declared(scene: Scene) -> dict:
    """What the bench tells the chain of itself (``ChainSettings`` fields): its digitizer's timing
    jitter (issue 12 case 7: it enters the range sigma), its laser (the LO x echo carrier beat is
    no line beyond coherence: case 4, speed unknown, not 0; the square stage ranges there) and its
    tone amplitudes, as a calibration on a reflector measures them (:func:`reference_amplitudes`:
    the static point's lines are checked against them). Not its synthesizers' drift
    (``tone_phase_sigma_rad``): the map's scenes have none, and a simulated drift is a random walk
    whose rms grows with the frame index (a bench declares its drift since calibration)."""
    return {"timing_jitter_s": scene.noise.trigger_jitter_s, "laser_linewidth_hz": scene.laser.linewidth_hz,
            "lo_path_difference_m": scene.paths.lo_path_difference_m,
            "tone_amplitudes": reference_amplitudes(reflector_scene(scene).model_dump_json())}


def reflector_scene(scene: Scene) -> Scene:
    """The bench of ``scene`` looking at one still reflector (its first target's range), an ideal
    laser, float volts and next to no noise (thermal noise of a front end at 1 mK: a noiseless
    quasi-CW record's gaps sit at its extremes, which validate takes for clipping): what a
    calibration of its tone amplitudes sees."""
    d = scene.model_dump()
    d["targets"] = [dict(d["targets"][0], velocity_mps=0.0, loss_db=60.0)]
    d["noise"] = {"thermal": True, "temperature_k": 1e-3}
    d["laser"]["linewidth_hz"] = 0.0
    d["digitizer"].update(adc_bits=None, full_scale_v=None)
    return scene_from_dict(d, origin=f"reflector of {scene.name}")


@functools.lru_cache(maxsize=64)
def reference_amplitudes(reflector_json: str) -> tuple[float, ...]:
    """The tone amplitudes the reflector scene (JSON, :func:`reflector_scene`) shows the chain
    (:func:`~mtcw_core.calibrate.tone_amplitudes`, one frame), cached per bench."""
    sc = Scene.model_validate_json(reflector_json)
    return tone_amplitudes(Simulator(sc, 0).frames(1))


def run_group(g: Group, profiles: tuple[str, ...], z_wrong: float = Z_WRONG) -> dict:
    """Simulate a group's frames once, run every profile, judge every frame; cells and frame rows."""
    sc = g.scene
    t0 = time.perf_counter()
    frames = list(Simulator(sc, g.seed).frames(g.frames))
    sim_s = (time.perf_counter() - t0) / max(g.frames, 1)
    bound = None if g.config.self_beat else predicted_bound(sc, g.seed)  # the LO-beat bound means nothing there
    tones = sorted(sc.tones_hz)
    lam_min = C / (2 * (tones[-1] - tones[0]))
    cells, rows = [], []
    known = declared(sc)
    # a tracked configuration's cells: balanced's points per frame, then the same with their range rate
    runs = [p for p in profiles if not g.config.track or p == "balanced"] + \
        ([accumulate_label(g.config.accumulate)] if g.config.accumulate else []) + \
        ([track_label(g.config.track)] if g.config.track else [])
    done: dict[str, list] = {}  # each profile's results, for the tracked cell
    first_snr = predicted_snr_db(sc, True, g.seed) if g.config.self_beat else (bound.line_snr_db if bound else None)
    must = must_find(sc, first_snr, g.config.self_beat, g.seed)
    pn = crb_phase_noise(g, bound)
    for prof in runs:
        chain = prof.split("+")[0]  # the chain's profile under an accumulated or tracked cell
        settings = get_profile(chain, **known)
        # case 9: the accumulator's points answer the truth averaged over the frames they rest on
        acc = Accumulator(AccumulateSettings(frames=g.config.accumulate), settings) if "+acc" in prof else None
        trk = (Tracker(TrackSettings(frames=g.config.track, max_speed_mps=TRACK_MAX_SPEED_MPS))
               if "+trk" in prof else None)
        verdicts, times, truths = [], [], {}
        for i, fr in enumerate(frames):
            t1 = time.perf_counter()
            if trk is not None:  # the profile's own results when it ran, else the chain's now
                base = done[chain][i] if chain in done else process_frame(fr, settings)
                res = trk.update(base)
            else:
                res = process_frame(fr, settings) if acc is None else acc.add(fr)
                done.setdefault(prof, []).append(res)
            times.append(time.perf_counter() - t1)
            truths[fr.seq] = fr.truth
            truth = fr.truth if acc is None else mean_truth([truths[q] for q in acc.window_seqs()])
            v = judge_frame(res, truth, z_wrong)
            verdicts.append(v)
            rows.append(_frame_row(g, prof, i, res.reason, v))
        cell = {
            "slice": g.config.slice, "config": g.config.label, "rung": g.rung, "snr_target_db": g.snr_target_db,
            "profile": prof, "samples": sc.digitizer.samples, "receiver": sc.receiver.kind,
            "linewidth_hz": sc.laser.linewidth_hz, "jitter_s": sc.noise.trigger_jitter_s,
            "n_targets": len(sc.targets), "loss_db": [t.loss_db for t in sc.targets],
            "velocity_mps": [t.velocity_mps for t in sc.targets], "first_moves": sc.targets[0].velocity_mps != 0,
            "predicted_snr_db": first_snr,
            "crb_range_m": bound.range_sigma_m if bound else None,
            "crb_speed_mps": bound.speed_sigma_mps if bound else None,
            "seed": g.seed, "sim_ms_per_frame": 1e3 * sim_s, "chain_ms_median": 1e3 * statistics.median(times),
            "note": g.config.note,
            **summarise(verdicts, len(sc.targets), must),
        }
        std = _first_target_efficiency(verdicts, lam_min)
        cell["range_std_m"] = std
        cell["range_std_over_crb"] = std / bound.range_sigma_m if (std is not None and bound) else None
        cell["crb_pn_range_m"] = pn
        cell["range_std_over_crb_pn"] = std / pn if (std is not None and pn) else None
        cell["misses"] = check_targets(cell)
        cells.append(cell)
    return {"cells": cells, "frames": rows}


def _frame_row(g: Group, profile: str, i: int, reason: str | None, v: FrameVerdict) -> dict:
    def worst(attr: str):
        zs = [abs(getattr(p, attr)) for p in v.points if getattr(p, attr) is not None]
        return round(max(zs), 3) if zs else None

    return {"slice": g.config.slice, "config": g.config.label, "rung": g.rung, "profile": profile, "frame": i,
            "status": v.status, "points": len(v.points), "missed": len(v.missed), "false_targets": v.false_targets,
            "flagged": v.flagged_points, "confident_wrong": int(v.confident_wrong),
            "confident_false": int(v.confident_false), "max_range_z": worst("range_z"), "max_speed_z": worst("speed_z"),
            "flags": ";".join(sorted({f for p in v.points for f in p.flags})), "reason": (reason or "")[:80]}


# -------------------------------------------------------------------------------------------
# the map
@dataclass
class MapSpec:
    """What to run: ``quick`` (CI) or the full grid; which slices; frames per cell; profiles."""

    quick: bool = False
    frames: int | None = None
    profiles: tuple[str, ...] = PROFILES
    slices: list[str] | None = None
    cases: bool = True
    jobs: int = field(default_factory=lambda: os.cpu_count() or 1)

    @property
    def frames_per_cell(self) -> int:
        return self.frames or (3 if self.quick else 16)


def map_configs(spec: MapSpec) -> list[Config]:
    """The rows ``spec`` asks for: the grid's slices, and issue 12's cases (full map only)."""
    configs = grid(spec.quick, spec.slices)
    if spec.cases and not spec.quick and (spec.slices is None or "cases" in spec.slices):
        configs += case_configs()
    return configs


def run_map(spec: MapSpec, progress=None, groups: list[Group] | None = None) -> dict:
    """Run the map (``groups``: its plan, if already made); a JSON-able dict with the cells, the
    per-frame rows and the run's size and time. Raises ValueError naming an unknown profile."""
    for p in spec.profiles:
        get_profile(p)
    configs = map_configs(spec)
    if groups is None:
        groups = plan(configs, spec.frames_per_cell)
    groups = sorted(groups, key=lambda g: -g.cost)
    t0 = time.perf_counter()
    cells, rows, errors = [], [], []
    if spec.jobs <= 1:
        for g in groups:
            out = run_group(g, spec.profiles)
            cells += out["cells"]
            rows += out["frames"]
            if progress:
                progress(g)
    else:
        with ProcessPoolExecutor(max_workers=spec.jobs) as pool:
            futs = {pool.submit(run_group, g, spec.profiles): g for g in groups}
            for f in as_completed(futs):
                try:
                    out = f.result()
                except Exception as err:  # one broken group must not lose the others' hours
                    g = futs[f]
                    errors.append(f"{g.config.key} {g.rung}: {type(err).__name__}: {err}")
                    print(f"honesty: {errors[-1]}", file=sys.stderr)
                    continue
                cells += out["cells"]
                rows += out["frames"]
                if progress:
                    progress(futs[f])
    order = {c.key: i for i, c in enumerate(configs)}
    cells.sort(key=lambda c: (order[f"{c['slice']}/{c['config']}"], _rung_order(c["rung"]), c["profile"]))
    wall = time.perf_counter() - t0
    return {"cells": cells, "frames": rows, "wall_s": wall, "errors": errors,
            "size": {"configs": len(configs), "groups": len(groups), "cells": len(cells),
                     "simulated_frames": sum(g.frames for g in groups),
                     "processed_frames": sum(g.frames for g in groups) * len(spec.profiles),
                     "profiles": list(spec.profiles), "jobs": spec.jobs, "quick": spec.quick}}


def _rung_order(rung: str) -> float:
    if rung.startswith("snr="):
        return -float(rung[4:])
    if rung.startswith("loss="):
        return float(rung[5:])
    return 0.0


def read_result(out: Path) -> dict:
    """A map's result as :func:`run_map` returned it, read back from ``out/cells.json`` and
    ``out/frames.csv.gz`` (to rewrite a report without running the map again)."""
    import csv
    import gzip
    import json

    result = json.loads((out / "cells.json").read_text())
    path = out / "frames.csv.gz"
    result["frames"] = list(csv.DictReader(gzip.open(path, "rt"))) if path.exists() else []
    return result


def main(argv: list[str] | None = None) -> None:
    """``mtcw-bench-honesty``: run the map and write its tables, heat maps and report."""
    import platform
    import shlex

    from tqdm import tqdm

    from .honesty_report import write_honesty_report

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="a small map for CI (2^16 samples, 2 rungs, 3 frames)")
    ap.add_argument("-o", "--out", type=Path, default=Path("out") / "honesty")
    ap.add_argument("--frames", type=int, default=None, help="frames per cell (default 16; quick 3)")
    ap.add_argument("--profiles", default=",".join(PROFILES), help="comma-separated profiles")
    ap.add_argument("--slices", default=None, help="comma-separated slices (length, receiver, laser, targets, "
                                                   "six-tone, jitter, quasi-cw, cases)")
    ap.add_argument("--no-cases", action="store_true", help="leave out issue 12's nine failure cases")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="worker processes")
    ap.add_argument("--report-only", action="store_true", help="rewrite the report from the cells.json and "
                                                               "frames.csv.gz already in --out (no run)")
    args = ap.parse_args(argv)
    if args.report_only:
        result = read_result(args.out)
        print(f"wrote {write_honesty_report(result, args.out)}")
        return
    spec = MapSpec(quick=args.quick, frames=args.frames, profiles=tuple(p.strip() for p in args.profiles.split(",")),
                   slices=[s.strip() for s in args.slices.split(",")] if args.slices else None,
                   cases=not args.no_cases, jobs=max(1, args.jobs))
    try:
        for p in spec.profiles:
            get_profile(p)
        t0 = time.perf_counter()
        groups = plan(map_configs(spec), spec.frames_per_cell)
    except ValueError as err:
        sys.exit(f"mtcw-bench-honesty: {err}")
    plan_s = time.perf_counter() - t0
    print(f"honesty: {len(groups)} groups planned in {plan_s:.0f} s", file=sys.stderr)
    bar = tqdm(total=len(groups), unit="group", desc="honesty", file=sys.stderr)

    def progress(g: Group) -> None:
        bar.set_postfix_str(f"{g.config.key} {g.rung}")
        bar.update(1)

    try:
        result = run_map(spec, progress, groups)
    except ValueError as err:
        sys.exit(f"mtcw-bench-honesty: {err}")
    bar.close()
    result["plan_s"] = plan_s
    result["machine"] = f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"
    result["command"] = "mtcw-bench-honesty " + " ".join(shlex.quote(a) for a in (argv if argv is not None
                                                                                      else sys.argv[1:]))
    path = write_honesty_report(result, args.out)
    s = result["size"]
    print(f"wrote {path} ({s['cells']} cells, {s['processed_frames']} processed frames, {result['wall_s']:.0f} s)")


__all__ = ["Config", "Group", "MapSpec", "grid", "map_configs", "case_scenes", "case_configs", "issue_scene",
           "case9_accumulate_configs", "accumulate_label", "track_configs", "track_label", "plan", "run_group",
           "run_map", "summarise", "must_find", "check_targets", "crb_phase_noise", "in_crb_domain", "predicted_bound", "predicted_snr_db", "with_targets", "shifted",
           "bin_speed_mps", "spacing_speed_mps", "base_scene", "self_beat_snr_db", "self_beat_amplitude_v",
           "loss_shift_for", "read_result", "main"]


if __name__ == "__main__":
    main()
