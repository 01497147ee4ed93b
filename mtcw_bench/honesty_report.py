"""The honesty map's output: ``cells.csv``/``cells.json``, ``frames.csv.gz``, heat maps and ``report.md``.

Heat maps (one panel per profile; a row per configuration, a column per rung of the loss ladder,
strongest echo on the left): the fraction of frames with a confident wrong or false answer (the
count written in the cell), the range and speed z-score spread (log colour, 1 is honest) and
the fraction of targets missed. The report lists the totals, the nine failure cases of issue 12,
the issue's targets with what the map measured, the cells that miss them, and where more
samples lost a target that fewer samples found.
"""

from __future__ import annotations

import math

import csv
import gzip
import io
import json
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy.stats import chi2, norm  # noqa: E402

from .honesty import MUST_FIND_SNR_DB, Z_MEAN_MAX, Z_STD_RANGE, Z_WRONG, _rung_order, z_in_band  # noqa: E402

CELL_COLS = ["slice", "config", "rung", "profile", "samples", "receiver", "linewidth_hz", "jitter_s", "n_targets",
             "loss_db", "velocity_mps", "predicted_snr_db", "frames", "ok", "no_target", "rejected", "points",
             "truths", "missed", "missed_must_find", "false_targets", "flagged_points", "confident_wrong",
             "confident_false", "confident_any", "flagged_wrong", "range_z_n", "range_z_mean", "range_z_std",
             "range_z_std_robust", "range_z_max", "speed_z_n", "speed_z_mean", "speed_z_std", "speed_z_std_robust", "speed_z_max",
             "range_z_unflagged_n", "range_z_unflagged_mean", "range_z_unflagged_std", "speed_z_unflagged_n",
             "speed_z_unflagged_mean", "speed_z_unflagged_std",
             "range_std_m", "crb_range_m", "range_std_over_crb", "crb_pn_range_m", "range_std_over_crb_pn", "crb_speed_mps", "chain_ms_median",
             "sim_ms_per_frame", "seed", "misses"]


def _flat(v):
    if isinstance(v, list):
        return ";".join(f"{x:g}" if isinstance(x, float) else str(x) for x in v)
    return v


def write_tables(result: dict, out: Path) -> None:
    """``cells.json`` (everything but the frame rows), ``cells.csv`` and ``frames.csv.gz``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "cells.json").write_text(json.dumps({k: v for k, v in result.items() if k != "frames"},
                                               separators=(",", ":"), default=str))
    with open(out / "cells.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=CELL_COLS, extrasaction="ignore")
        w.writeheader()
        for c in result["cells"]:
            w.writerow({k: _flat(c.get(k)) for k in CELL_COLS})
    rows = result["frames"]
    if rows:
        # mtime 0: the same rows give the same bytes (a rewritten report leaves the file alone in git)
        with open(out / "frames.csv.gz", "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0) as gz, \
                io.TextIOWrapper(gz, newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)


def _fmt(v, spec: str = ".2f") -> str:
    if v is None:
        return "–"
    if isinstance(v, float) and not np.isfinite(v):
        return "inf"
    return format(v, spec)


# -------------------------------------------------------------------------------------------
# heat maps
def _matrix(cells: list[dict], profile: str, value) -> tuple[list[str], list[str], np.ndarray, list[list]]:
    rows = []
    for c in cells:
        k = f"{c['slice']}: {c['config']}"
        if k not in rows:
            rows.append(k)
    rungs = sorted({c["rung"] for c in cells}, key=_rung_order)
    m = np.full((len(rows), len(rungs)), np.nan)
    notes = [[""] * len(rungs) for _ in rows]
    for c in cells:
        if c["profile"] != profile:
            continue
        i, j = rows.index(f"{c['slice']}: {c['config']}"), rungs.index(c["rung"])
        v, note = value(c)
        m[i, j] = np.nan if v is None else v
        notes[i][j] = note
    return rows, rungs, m, notes


def _heatmap(cells: list[dict], profiles: list[str], value, path: Path, title: str, cmap: str, vmin: float,
             vmax: float, cbar: str) -> None:
    rows = list(dict.fromkeys(f"{c['slice']}: {c['config']}" for c in cells))
    rungs = sorted({c["rung"] for c in cells}, key=_rung_order)
    fig, axes = plt.subplots(1, len(profiles), figsize=(2.2 + 0.55 * len(rungs) * len(profiles) + 2.5,
                                                         1.6 + 0.19 * len(rows)), squeeze=False, sharey=True)
    im = None
    for ax, prof in zip(axes[0], profiles):
        _, _, m, notes = _matrix(cells, prof, value)
        cm = plt.get_cmap(cmap).with_extremes(bad="#d0d0d0")  # grey: no such cell (a rung the row lacks)
        im = ax.imshow(np.ma.masked_invalid(m), aspect="auto", cmap=cm, vmin=vmin, vmax=vmax,
                       interpolation="nearest")
        for i in range(m.shape[0]):
            for j in range(m.shape[1]):
                if notes[i][j]:
                    ax.text(j, i, notes[i][j], ha="center", va="center", fontsize=5)
        ax.set_xticks(range(len(rungs)), [r.replace("snr=", "") for r in rungs], fontsize=6, rotation=90)
        ax.set_title(prof, fontsize=9)
        ax.set_xlabel("rung: first target's line SNR (dB) / loss", fontsize=6)
    axes[0][0].set_yticks(range(len(rows)), rows, fontsize=6)
    fig.suptitle(title, fontsize=10)
    if im is not None:
        cb = fig.colorbar(im, ax=axes[0].tolist(), fraction=0.02, pad=0.01)
        cb.set_label(cbar, fontsize=7)
        cb.ax.tick_params(labelsize=6)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def _cw(c: dict):
    f = c["frames"]
    return (c["confident_any"] / f if f else None), (str(c["confident_any"]) if c["confident_any"] else "")


def _log_std(key: str):
    def v(c: dict):
        s = c.get(key)
        if s is None or not np.isfinite(s) or s <= 0:
            return None, ""
        return float(np.log10(s)), (f"{s:.2g}" if not Z_STD_RANGE[0] <= s <= Z_STD_RANGE[1] else "")
    return v


def _missed(c: dict):
    t = c["truths"]
    return (c["missed"] / t if t else None), (str(c["missed"]) if c["missed"] else "")


def plot_heatmaps(cells: list[dict], out: Path) -> list[str]:
    """The four heat maps (PNG); returns their file names."""
    grid_cells = [c for c in cells if c["slice"] != "cases"]
    if not grid_cells:
        return []
    profiles = list(dict.fromkeys(c["profile"] for c in grid_cells))
    _heatmap(grid_cells, profiles, _cw, out / "confident_wrong.png",
             f"frames with a confident wrong or false answer (unflagged, |z| > {Z_WRONG:g} or no truth): fraction, "
             "count written", "Reds", 0, 1, "fraction of frames")
    _heatmap(grid_cells, profiles, _log_std("range_z_std"), out / "range_z_std.png",
             "range z-score std (log10; 0 = honest; value written outside 0.8-1.25)", "RdBu_r", -2, 2,
             "log10 std(z)")
    _heatmap(grid_cells, profiles, _log_std("speed_z_std"), out / "speed_z_std.png",
             "speed z-score std over measured speeds (log10; value written outside 0.8-1.25)", "RdBu_r", -2, 2,
             "log10 std(z)")
    _heatmap(grid_cells, profiles, _missed, out / "missed.png", "targets missed: fraction, count written",
             "Purples", 0, 1, "fraction of truth targets")
    return ["confident_wrong.png", "range_z_std.png", "speed_z_std.png", "missed.png"]


# -------------------------------------------------------------------------------------------
# the report
def _totals(cells: list[dict]) -> dict:
    keys = ("frames", "ok", "confident_wrong", "confident_false", "confident_any", "flagged_wrong", "missed",
            "false_targets", "flagged_points", "truths")
    return {k: sum(c[k] for c in cells) for k in keys}


def monotonic_violations(cells: list[dict], drop: float = 0.25) -> list[dict]:
    """Where a longer record found the (same) target in fewer frames than a shorter one, at the same
    losses: the ``length`` and ``six-tone`` slices, and the 5.3 GHz static rows."""
    by: dict[tuple, dict[int, dict]] = defaultdict(dict)
    for c in cells:
        label = c["config"]
        if c["slice"] in ("length", "six-tone"):
            speed = label.split(" ", 1)[1]
            if speed in ("v=0.5 bin", "v=6 bins"):  # these speeds scale with N: not the same target
                continue
        elif c["slice"] == "laser" and label.startswith("5.3 GHz") and label.endswith(" v=0"):
            speed = "5.3 GHz v=0"
        else:
            continue
        by[(c["slice"], speed, c["rung"], c["profile"], tuple(c["loss_db"]))][c["samples"]] = c
    out = []
    for (sl, speed, rung, prof, loss), per_n in by.items():
        ns = sorted(per_n)
        for a, b in zip(ns, ns[1:]):
            fa = 1 - per_n[a]["missed"] / per_n[a]["truths"]
            fb = 1 - per_n[b]["missed"] / per_n[b]["truths"]
            if fb < fa:
                out.append({"slice": sl, "speed": speed, "rung": rung, "profile": prof, "loss_db": loss[0],
                            "short": a, "long": b, "found_short": fa, "found_long": fb, "large": fa - fb >= drop})
    return out


def _z_cell(c: dict, k: str) -> str:
    return f"{_fmt(c[f'{k}_z_mean'])} / {_fmt(c[f'{k}_z_std'])} / {_fmt(c[f'{k}_z_max'], '.1f')}"


def z_band_probability(n: int) -> float:
    """The chance that ``n`` z-values drawn from N(0, 1) -- a sigma exactly right -- meet the
    cell target: ``|mean| < Z_MEAN_MAX`` and sample std (ddof 1) within ``Z_STD_RANGE`` (mean and
    std of normal samples are independent: ``mean ~ N(0, 1/n)``, ``(n-1) s^2 ~ chi2(n-1)``)."""
    if n < 2:
        return 0.0
    p_mean = 2 * norm.cdf(Z_MEAN_MAX * np.sqrt(n)) - 1
    lo, hi = ((n - 1) * Z_STD_RANGE[0] ** 2, (n - 1) * Z_STD_RANGE[1] ** 2)
    return float(p_mean * (chi2.cdf(hi, n - 1) - chi2.cdf(lo, n - 1)))


def z_scatter_inconsistent(n: int, mean: float, std: float | None, alpha: float = 0.01) -> bool:
    """Whether ``n`` z-values with this mean and std (ddof 1) are unlikely under N(0, 1): their
    ``sum(z^2) = (n-1) std^2 + n mean^2 ~ chi2(n)``, two-sided at ``alpha``."""
    if n < 2 or std is None:
        return False
    q = (n - 1) * std**2 + n * mean**2
    return bool(chi2.cdf(q, n) < alpha / 2 or chi2.sf(q, n) < alpha / 2)


#: the largest share of flagged points (``cycle_ambiguous`` at a small margin: honest, but no
#: number to use) a loss may have and still count toward the 5.3 GHz laser's reach
REACH_MAX_FLAGGED = 0.1


def coherence_reach(cells: list[dict]) -> dict[int, tuple[float, float, int, int]]:
    """Per record length, the echo loss (dB) up to which every cell of ``cells`` (one laser, one
    profile, a static target) at that or a lower loss had every frame ok, at most
    :data:`REACH_MAX_FLAGGED` of its points flagged, a range scatter <= 1 cm and nothing
    confident wrong (-inf when the lowest fails), with the largest loss mapped and the flagged
    points and frames up to the reach: {samples: (reach, largest, flagged, frames)}."""
    out: dict[int, tuple[float, float, int, int]] = {}
    for n in sorted({c["samples"] for c in cells}):
        row = sorted((c for c in cells if c["samples"] == n), key=lambda c: c["loss_db"][0])
        reach, flagged, frames = -math.inf, 0, 0
        for c in row:
            if not (c["ok"] == c["frames"] and c["confident_any"] == 0
                    and c["flagged_points"] <= REACH_MAX_FLAGGED * c["frames"]
                    and c["range_std_m"] is not None and c["range_std_m"] <= 0.01):
                break
            reach, flagged, frames = c["loss_db"][0], flagged + c["flagged_points"], frames + c["frames"]
        out[n] = (reach, row[-1]["loss_db"][0], flagged, frames)
    return out


def _z_scatter(cells: list[dict], p: str) -> tuple[list[dict], float, list[dict]]:
    """Of ``cells``, those with at least 5 z-values of prefix ``p`` (``range_z``, ``speed_z_unflagged``
    ...), how many of them a sigma exactly right would leave outside the band by chance, and those
    whose z scatter is inconsistent with 1 at 1 %. Cells without the columns (older maps) are left out."""
    judged = [c for c in cells if (c.get(f"{p}_n") or 0) >= 5 and c.get(f"{p}_std") is not None]
    chance = sum(1 - z_band_probability(c[f"{p}_n"]) for c in judged)
    odd = [c for c in judged if z_scatter_inconsistent(c[f"{p}_n"], c[f"{p}_mean"], c[f"{p}_std"])]
    return judged, chance, odd


def _unflagged_row(above: list[dict], k: str, name: str) -> str:
    """The z target's diagnostic twin over each cell's unflagged points alone (``*_z_unflagged_*``:
    a flag says the number may be wrong, so only an unflagged point's sigma is a claim); absent
    from maps made before those columns."""
    u = f"{k}_unflagged"
    judged, chance, odd = _z_scatter(above, u)
    if not judged:
        return f"| ... {name}, unflagged points only | not in this map's cells | (diagnostic) |"
    within = [c for c in judged if z_in_band(c[f"{u}_mean"], c[f"{u}_std"])]
    return (f"| ... {name}, unflagged points only (a flag says the number may be wrong: only an unflagged "
            f"point's sigma is a claim) | {len(within)} of {len(judged)} cells within (median z std "
            f"{_fmt(float(np.median([c[f'{u}_std'] for c in judged])))}); by chance {chance:.0f} outside; "
            f"{len(odd)} inconsistent with 1 at 1 % ({sum(1 for c in odd if c[f'{u}_std'] < 1)} conservative) "
            f"| (diagnostic) |")


def write_honesty_report(result: dict, out: Path) -> Path:
    """Tables, heat maps and ``report.md`` under ``out``; returns the report's path."""
    write_tables(result, out)
    cells = result["cells"]
    figs = plot_heatmaps(cells, out)
    grid_cells = [c for c in cells if c["slice"] != "cases"]
    case_cells = [c for c in cells if c["slice"] == "cases"]
    s = result["size"]
    L = ["# Honesty map (issue 12)", "",
         f"Command: `{result.get('command', 'mtcw bench --honesty')}`", "",
         f"Machine: {result.get('machine', 'unknown')}; {s['jobs']} worker processes; wall time "
         f"{result['wall_s'] / 60:.1f} min" + (f" (+ {result['plan_s'] / 60:.1f} min planning the loss ladder)"
                                               if result.get("plan_s") else "") + ".", "",
         f"Size: {s['configs']} configurations, {s['groups']} (configuration, loss) groups, {s['cells']} cells "
         f"(x profiles {', '.join(s['profiles'])}); {s['simulated_frames']} simulated frames, "
         f"{s['processed_frames']} processed frames (frame x profile).", "",
         "## How to read it", "",
         f"- **z** = (estimate - truth) / the point's own sigma; range errors are wrapped into +-half the "
         f"unambiguous range (CW). Speed z compares |v| (signed v for IQ, which reports the direction); a point "
         f"reported `static` says 0 with the smallest detectable speed as its sigma: its z counts for the largest "
         f"|z| and for confident-wrong, not for the speed mean/std.",
         f"- **confident wrong** (issue 12): status ok, no flag (`near_edge`, `cycle_ambiguous`, `blended`), "
         f"|z| > {Z_WRONG:g} on range, speed or (tracked cells) range rate. **confident false**: an unflagged point that answers no truth (a "
         f"ghost). Points and truths are paired one to one: those agreeing on both range and speed first, then "
         f"nearest in speed. **flagged wrong**: a wrong number beside a flag (counted, not excused: issue 12 "
         f"case 3).",
         f"- **above threshold**: the bound's median line SNR of the first target (from the truth, white noise "
         f"only) ≥ {MUST_FIND_SNR_DB:g} dB, 3 dB above the chain's line threshold. The z and missed targets are "
         f"checked only there; the confident-wrong target everywhere.",
         "- Rungs: `snr=X` is the loss at which the first target's predicted line SNR is X dB (at the 2^16 row for "
         "`length`/`six-tone`, so longer records there are 6 and 12 dB stronger); `loss=X` a fixed loss; "
         "`as is` the scene as the issue states it.", ""]
    # totals
    L += ["## Totals", "", "| part | profile | frames | confident wrong | confident false | either | flagged wrong "
          "| missed / truths | false targets |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for part, cs in (("map", grid_cells), ("issue cases", case_cells)):
        for prof in dict.fromkeys(c["profile"] for c in cs):
            t = _totals([c for c in cs if c["profile"] == prof])
            L.append(f"| {part} | {prof} | {t['frames']} | {t['confident_wrong']} | {t['confident_false']} | "
                     f"{t['confident_any']} | {t['flagged_wrong']} | {t['missed']} / {t['truths']} | "
                     f"{t['false_targets']} |")
        if cs:
            t = _totals(cs)
            L.append(f"| {part} | **all** | {t['frames']} | **{t['confident_wrong']}** | **{t['confident_false']}** | "
                     f"**{t['confident_any']}** | {t['flagged_wrong']} | {t['missed']} / {t['truths']} | "
                     f"{t['false_targets']} |")
    L.append("")
    if case_cells:
        L += ["## Issue 12's nine failures (as the issue states them)", "",
              "| case | profile | frames | ok | confident wrong | confident false | flagged wrong | missed | "
              "range z mean / std / max | speed z mean / std / max |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
        for c in case_cells:
            L.append(f"| {c['config']} ({c['note']}) | {c['profile']} | {c['frames']} | {c['ok']} | "
                     f"{c['confident_wrong']} | {c['confident_false']} | {c['flagged_wrong']} | {c['missed']} | "
                     f"{_z_cell(c, 'range')} | {_z_cell(c, 'speed')} |")
        L.append("")
    tracked = [c for c in cells if c.get("rate_z_n")]
    if tracked:
        L += ["## Range rate over frames (`mtcw_core.ranging.track`)", "",
              "Each point's range rate, the weighted slope of its track's last ranges over their trigger times, "
              "judged against the truth's velocity (positive receding); its |z| > 5 on an unflagged point counts as "
              "confident wrong above. Consecutive points share most of their window, so a cell's rate z values are "
              "strongly correlated: its std says less than the number of points suggests.", "",
              "| configuration | profile | frames | points with a rate | confident wrong | rate z mean / std / max |",
              "| --- | --- | --- | --- | --- | --- |"]
        for c in tracked:
            L.append(f"| {c['config']} ({c['note']}) | {c['profile']} | {c['frames']} | {c['rate_z_n']} | "
                     f"{c['confident_wrong']} | {_z_cell(c, 'rate')} |")
        L.append("")
    # targets
    L += ["## Issue 12's targets", "", "| target | measured | met? |", "| --- | --- | --- |"]
    t = _totals(cells)
    L.append(f"| 0 confident-wrong frames over the whole map | {t['confident_wrong']} confident wrong + "
             f"{t['confident_false']} confident false ({t['confident_any']} frames) of {t['frames']} | "
             f"{'met' if t['confident_any'] == 0 else 'missed'} |")
    L.append(f"| ≥ 20,000 frames in the full run | {s['processed_frames']} processed ({s['simulated_frames']} "
             f"simulated) | {'met' if s['processed_frames'] >= 20000 else 'missed'} |")
    above = [c for c in grid_cells if c.get("predicted_snr_db") is not None and c["predicted_snr_db"] >= MUST_FIND_SNR_DB]
    for k, name in (("range_z", "range"), ("speed_z", "speed")):
        judged, chance, odd = _z_scatter(above, k)
        bad = [c for c in judged if k in c["misses"]]
        L.append(f"| {name}: abs(mean z) < {Z_MEAN_MAX} and z std {Z_STD_RANGE[0]}–{Z_STD_RANGE[1]} in every cell "
                 f"above threshold | {len(judged) - len(bad)} of {len(judged)} cells within (median z std "
                 f"{_fmt(float(np.median([c[f'{k}_std'] for c in judged])) if judged else None)}); a sigma exactly "
                 f"right would leave {chance:.0f} outside by chance (few z-values per cell); "
                 f"{len(odd)} cells' z scatter is inconsistent with 1 at 1 % "
                 f"({sum(1 for c in odd if c[f'{k}_std'] < 1)} too small: sigma conservative) | "
                 f"{'met' if not bad else f'missed in {len(bad)} cells'} |")
        L.append(_unflagged_row(above, k, name))
    mm = [c for c in grid_cells if "missed" in c["misses"]]
    L.append(f"| no missed target at line SNR ≥ {MUST_FIND_SNR_DB:g} dB (each target's own) | "
             f"{sum(c.get('missed_must_find', c['missed']) for c in mm)} targets "
             f"missed in {len(mm)} of {len(above)} cells | {'met' if not mm else 'missed'} |")
    mv = monotonic_violations(cells)
    L.append(f"| more samples never lose a target | {len(mv)} (record, rung, profile) pairs found fewer frames at "
             f"the longer record ({sum(v['large'] for v in mv)} by ≥ 25 points) | {'met' if not mv else 'missed'} |")
    crb = [c for c in cells if c["profile"] == "balanced" and c.get("first_moves") and c.get("range_std_over_crb")
           and 40 <= c["loss_db"][0] <= 80 and c["slice"] != "jitter"]
    if crb:
        worst = max(crb, key=lambda c: c["range_std_over_crb"])
        L.append(f"| `balanced` sigma ≤ 1.3× CRB on movers at 40–80 dB | {sum(c['range_std_over_crb'] <= 1.3 for c in crb)}"
                 f" of {len(crb)} cells; median {np.median([c['range_std_over_crb'] for c in crb]):.2f}×, worst "
                 f"{worst['range_std_over_crb']:.1f}× ({worst['slice']}: {worst['config']}, {worst['rung']}) | "
                 f"{'met' if worst['range_std_over_crb'] <= 1.3 else 'missed'} |")
        pn = [c for c in crb if c["range_std_over_crb"] > 1.3 and c.get("range_std_over_crb_pn") is not None]
        if pn:
            L.append(f"| ... of its misses, within 1.3× the bound with the laser's phase-noise leakage as noise "
                     f"(`evaluate.phase_noise_bound`: not a lower bound, what the white-noise bound leaves out) | "
                     f"{sum(c['range_std_over_crb_pn'] <= 1.3 for c in pn)} of {len(pn)} with a linewidth; median "
                     f"{np.median([c['range_std_over_crb_pn'] for c in pn]):.2f}× | (diagnostic) |")
    lc = [c for c in cells if c["slice"] == "laser" and c["linewidth_hz"] >= 1e9 and c["n_targets"] == 1
          and c["velocity_mps"][0] == 0 and c["profile"] == "balanced"]
    if lc:
        reach = coherence_reach(lc)
        parts = [f"{n} samples: {v:.0f} dB of {top:.0f} dB mapped ({fl} of {fr} flagged)"
                 for n, (v, top, fl, fr) in sorted(reach.items())]
        L.append(f"| 5.3 GHz, 500× L_coh: sigma ≤ 1 cm to ≥ 40 dB in one frame | `balanced`, the loss up to which "
                 f"every mapped loss has every frame ok, at most {REACH_MAX_FLAGGED:.0%} flagged, range std ≤ 1 cm "
                 f"and nothing confident wrong: {', '.join(parts) or 'none'} | "
                 f"{'met' if reach and all(r[0] >= 40 for r in reach.values()) else 'missed'} |")
    L.append("")
    # cells that miss
    L += ["## Cells that miss a target, by slice and profile", "",
          "| slice | profile | cells | confident wrong | confident false | missed | range z | speed z | crb |",
          "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for sl in dict.fromkeys(c["slice"] for c in cells):
        for prof in dict.fromkeys(c["profile"] for c in cells):
            cs = [c for c in cells if c["slice"] == sl and c["profile"] == prof]
            if not cs:
                continue
            n = {k: sum(k in c["misses"] for c in cs) for k in
                 ("confident_wrong", "confident_false", "missed", "range_z", "speed_z", "crb")}
            L.append(f"| {sl} | {prof} | {len(cs)} | {n['confident_wrong']} | {n['confident_false']} | {n['missed']} | "
                     f"{n['range_z']} | {n['speed_z']} | {n['crb']} |")
    L += ["", "### Worst cells (most confident wrong or false frames)", "",
          "| slice | config | rung | profile | loss dB | pred. SNR | ok/frames | conf. wrong | conf. false | "
          "range z mean / std / max | speed z mean / std / max | misses |",
          "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    worst = sorted((c for c in grid_cells if c["confident_any"]), key=lambda c: -c["confident_any"])[:40]
    for c in worst:
        L.append(f"| {c['slice']} | {c['config']} | {c['rung']} | {c['profile']} | "
                 f"{'/'.join(f'{x:.0f}' for x in c['loss_db'])} | {_fmt(c['predicted_snr_db'], '.0f')} | "
                 f"{c['ok']}/{c['frames']} | {c['confident_wrong']} | {c['confident_false']} | {_z_cell(c, 'range')} | "
                 f"{_z_cell(c, 'speed')} | {', '.join(c['misses'])} |")
    if mv:
        L += ["", "### More samples lost a target", "",
              "| slice | speed | rung | loss dB | profile | N short → long | found short → long |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
        for v in sorted(mv, key=lambda v: -(v["found_short"] - v["found_long"]))[:30]:
            L.append(f"| {v['slice']} | {v['speed']} | {v['rung']} | {v['loss_db']:.0f} | {v['profile']} | "
                     f"{v['short']} → {v['long']} | {v['found_short']:.2f} → {v['found_long']:.2f} |")
    if result.get("errors"):
        L += ["", "## Groups that did not run", ""] + [f"- {e}" for e in result["errors"]]
    if figs:
        L += ["", "## Heat maps", ""] + [f"![{f}]({f})" for f in figs]
    L += ["", "## Files", "",
          "`cells.csv` / `cells.json`: one row per cell (all the numbers above); `frames.csv.gz`: one row per "
          "processed frame (status, points, missed, false, flags, largest |z|, the chain's reason).", ""]
    path = out / "report.md"
    path.write_text("\n".join(L) + "\n")
    return path


__all__ = ["write_honesty_report", "write_tables", "plot_heatmaps", "monotonic_violations"]
