"""``mtcw bench`` output: a CSV/JSON table, PNG plots and a Markdown report.

The figures: the Pareto front (time per frame vs range error per profile), sigma vs SNR with the
Cramér–Rao bound, outlier rate vs SNR for ``seed`` vs ``ml``, and the simulator's cost against
scene complexity. Targets of the benchmark issue are checked against the numbers and the report
says by how much each is met or missed.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mtcw_core.chain import STAGE_NAMES  # noqa: E402
from mtcw_core.profiles import PROFILES  # noqa: E402

from .grid import NOISY_SPREAD, UNACCOUNTED  # noqa: E402

_COLS = ["scene", "loss_db", "samples", "profile", "method", "frames", "repeats", "median_time_s", "time_spread",
         "frames_per_s", "time_over_rfft", "ratio_spread", "ratio_noisy", "time_over_rfft_volts", "time_over_rfft_raw",
         "time_over_pass", "range_bias_m", "range_sigma_m", "reported_sigma_m", "crb_range_m",
         "sigma_over_crb", "line_snr_db", "outlier_rate", "speed_bias_mps", "speed_sigma_mps", "crb_speed_mps",
         "peak_memory_mb", "peak_memory_x_f64", "frame_f64_mb", "warmup_retained_mb", "sim_s_per_frame"]
_STAGE_COLS = [f"stage_{k}_s" for k in (*STAGE_NAMES, UNACCOUNTED)]

#: The chain's speed targets of issue 16 (item 2): (scene, profile, at most this many float64 rffts).
SPEED_TARGETS: tuple[tuple[str, str, float], ...] = tuple(
    (scene, prof, lim) for scene in ("cw-bench", "moving-target", "six-tone")
    for prof, lim in (("fast", 0.5), ("balanced", 1.0), ("accurate", 2.0)))
#: Issue 16 item 4: peak memory per frame at most this many times the frame's float64 size...
MEMORY_LIMIT_X_F64 = 4.0
#: ... except for these profiles (``seed`` resamples to 2^23 points by design).
MEMORY_EXEMPT = ("seed",)
#: The record length the targets are set at.
TARGET_SAMPLES = 1_000_000
#: Issue 16 item 3: 2 workers on 2 cores reach at least this multiple of one worker's frames/s.
STREAM_SCALING = 1.6


def write_tables(result: dict, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(result, indent=1, default=str))
    with open(out / "results.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=_COLS + _STAGE_COLS, extrasaction="ignore")
        w.writeheader()
        for c in result["cells"]:
            w.writerow(c)


def _fmt(v, spec: str = ".3g") -> str:
    return "–" if v is None else format(v, spec)


def _plot_pareto(cells: list[dict], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for c in cells:
        if c["median_time_s"] is None or c["range_sigma_m"] is None:
            continue
        mk = "o" if c["method"] == "ml" else "s"
        ax.loglog(1e3 * c["median_time_s"], abs(c["range_bias_m"]) + c["range_sigma_m"], mk, ms=7,
                  label=f"{c['profile']}/{c['method']}")
        ax.annotate(f"{c['profile']}/{c['method']}", (1e3 * c["median_time_s"], abs(c["range_bias_m"]) + c["range_sigma_m"]),
                    fontsize=7, xytext=(4, 2), textcoords="offset points")
    ax.set_xlabel("median time per frame (ms)")
    ax.set_ylabel("|bias| + sigma of range (m)")
    ax.set_title("speed vs accuracy (lower left is better)")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_vs_snr(cells: list[dict], key: str, path: Path, ylabel: str, title: str, log: bool,
                 bound_key: str | None = None) -> None:
    """``key`` against the truth's line SNR, one curve per scene/profile/method (and the bound)."""
    fig, ax = plt.subplots(figsize=(9.5, 4.8))
    plot = ax.semilogy if log else ax.plot
    for scene, prof, meth in sorted({(c["scene"], c["profile"], c["method"]) for c in cells}):
        pts = sorted((c["line_snr_db"], c[key]) for c in cells
                     if (c["scene"], c["profile"], c["method"]) == (scene, prof, meth)
                     and c.get("line_snr_db") is not None and c[key] is not None and (c[key] or not log))
        if len(pts) >= 2:
            plot(*zip(*pts), "o-" if meth == "ml" else "s--", ms=4, label=f"{scene} {prof}/{meth}")
    for scene in sorted({c["scene"] for c in cells}) if bound_key else ():
        b = sorted({(c["line_snr_db"], c[bound_key]) for c in cells if c["scene"] == scene and c.get(bound_key)})
        if len(b) >= 2:
            plot(*zip(*b), "k--", lw=1.2, label=f"{scene} CRB")
    ax.set_xlabel("median line SNR (dB, from truth)")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=6, loc="center left", bbox_to_anchor=(1.01, 0.5), ncol=1)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_sim_cost(sim: list[dict], rfft_s: float | None, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    labels = [s["scene"] for s in sim]
    ms = [1e3 * s["sim_s_per_frame"] for s in sim]
    ax.barh(range(len(ms)), ms, color="tab:blue")
    ax.set_yticks(range(len(ms)), labels, fontsize=7)
    ax.invert_yaxis()
    if rfft_s:
        ax.axvline(1e3 * rfft_s, color="k", ls="--", lw=1, label="one rfft of the frame")
        ax.axvline(10e3 * rfft_s, color="r", ls=":", lw=1, label="10 rfft (target for the first bar)")
        ax.legend(fontsize=7)
    ax.set_xlabel("simulation time per frame (ms)")
    ax.set_title(f"simulator cost vs what the scene models ({sim[0]['samples']} samples)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _pct(v: float | None) -> str:
    return "–" if v is None else ("inf" if v == float("inf") else f"{100 * v:.0f} %")


def verdict(value: float | None, limit: float) -> str:
    """'met (x % under)' or 'missed by r× (+x %)' for a measured value against an upper limit."""
    if value is None:
        return "not measured"
    if value <= limit:
        return f"met ({100 * (1 - value / limit):.0f} % under)"
    over = 100 * (value / limit - 1)
    return f"missed by {over:.{0 if over >= 10 else 1 if over >= 0.1 else 3}f} % ({value / limit:.{2 if over >= 1 else 4}f}× the limit)"


def target_cell(cells: list[dict], scene: str, profile: str) -> dict | None:
    """The cell a target reads for a scene and profile: the profile's own cycle-resolution method
    (any method if that one was not run), at the lowest echo loss run (most frames ranged)."""
    cs = [c for c in cells if c["scene"] == scene and c["profile"] == profile]
    own = PROFILES[profile].method if profile in PROFILES else None
    cs = [c for c in cs if c["method"] == own] or cs
    return min(cs, key=lambda c: (c["loss_db"], c["method"])) if cs else None


def _largest_stage(c: dict) -> str:
    st = c.get("stage_s") or {}
    parts = {k: v for k, v in st.items() if k != "total"}
    if not parts:
        return ""
    k = max(parts, key=parts.get)
    rfft = (c.get("reference_s") or {}).get("fft_f64")
    tail = f" = {parts[k] / rfft:.2f}× rfft" if rfft else ""
    return f"largest stage: {k} {1e3 * parts[k]:.1f} ms{tail}"


def speed_target_rows(cells: list[dict]) -> list[dict]:
    """Issue 16 item 2: one row per (scene, profile) target, read from :func:`target_cell`.

    Each row: ``target``, ``scene``, ``cell`` (loss, method, samples), ``median`` (× one float64
    rfft, median of the per-repeat ratios), ``spread`` and ``noisy`` (see
    :func:`mtcw_bench.grid.ratio_stats`), ``verdict`` and ``why`` (the largest stage).
    """
    rows = []
    for scene, prof, lim in SPEED_TARGETS:
        c = target_cell(cells, scene, prof)
        row = {"target": f"`{prof}` ≤ {lim:g}× one float64 rfft", "scene": scene, "profile": prof, "limit": lim,
               "cell": None, "median": None, "spread": None, "noisy": None, "verdict": "not run", "why": ""}
        if c is not None:
            row.update(cell=f"{c['loss_db']:g} dB, {c['method']}, {c['samples']} samples, {c.get('repeats', c['frames'])} repeats",
                       median=c.get("time_over_rfft"), spread=c.get("ratio_spread"), noisy=c.get("ratio_noisy"),
                       verdict=verdict(c.get("time_over_rfft"), lim), why=_largest_stage(c))
            if c.get("time_over_rfft_pocketfft") is not None:  # another backend: the default install's reference too
                row["why"] += (f"; × pocketfft's float64 rfft ({1e3 * c['pocketfft_rfft_s']:.1f} ms): "
                               f"{c['time_over_rfft_pocketfft']:.2f}")
            if c["samples"] != TARGET_SAMPLES:
                row["verdict"] += f" (indicative: {c['samples']} samples, the target is set at {TARGET_SAMPLES})"
        rows.append(row)
    return rows


def memory_target_rows(cells: list[dict]) -> list[dict]:
    """Issue 16 item 4: per profile, the worst peak memory per frame over every cell of the run,
    as a multiple of the frame's own float64 size (``seed`` is shown, exempt by design)."""
    rows = []
    for prof in sorted({c["profile"] for c in cells}, key=lambda p: list(PROFILES).index(p) if p in PROFILES else 99):
        cs = [c for c in cells if c["profile"] == prof and c.get("peak_memory_x_f64") is not None]
        if not cs:
            continue
        w = max(cs, key=lambda c: c["peak_memory_x_f64"])
        exempt = prof in MEMORY_EXEMPT
        rows.append({"target": f"`{prof}` peak memory ≤ {MEMORY_LIMIT_X_F64:g}× the frame in float64"
                               + (" (exempt: resamples to 2^23 by design)" if exempt else ""),
                     "profile": prof, "worst_x": w["peak_memory_x_f64"], "worst_mb": w["peak_memory_mb"],
                     "cell": f"{w['scene']}, {w['loss_db']:g} dB, {w['method']}, {w['samples']} samples",
                     "verdict": "exempt" if exempt else verdict(w["peak_memory_x_f64"], MEMORY_LIMIT_X_F64)})
    return rows


def _num(d: dict, *keys):
    """d[k0][k1]... as a float, or None where absent or not a number (stream.json is read defensively)."""
    v = d
    for k in keys:
        if not isinstance(v, dict) or k not in v:
            return None
        v = v[k]
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def _cpu_fields(row: dict) -> str:
    """CPU per published frame of every process (``throughput.cpu.<process>.cpu_s_per_frame.median``,
    mtcw-bench-stream's layout), or else whatever CPU figures the row carries (keys naming 'cpu')."""
    cpu = (row.get("throughput") or {}).get("cpu") if isinstance(row.get("throughput"), dict) else None
    if isinstance(cpu, dict):
        parts = []
        for name, v in cpu.items():
            med = _num(v, "cpu_s_per_frame", "median") if isinstance(v, dict) else None
            if med is None and isinstance(v, dict):
                med = _num(v, "cpu_s_per_frame")
            if med is not None:
                parts.append(f"{'workers' if name == 'workers_total' else name} {1e3 * med:.1f}")
        if parts:
            return ", ".join(parts) + " ms"
    found = []

    def walk(d, path):
        if isinstance(d, dict):
            for k, v in d.items():
                walk(v, path + [str(k)])
        elif isinstance(d, (int, float)) and not isinstance(d, bool) and any("cpu" in p.lower() for p in path):
            name = ".".join(path[1:] if len(path) > 1 else path)
            in_s = name.endswith("_s") or "_s_per_" in name  # seconds by the project's unit suffix
            found.append(f"{name} {1e3 * d:.1f} ms" if in_s else f"{name} {d:.3g}")

    walk(row.get("throughput", {}), ["throughput"])
    walk({k: v for k, v in row.items() if k not in ("throughput", "latency_at_80pct")}, ["row"])
    return "; ".join(found)


def stream_section(stream: dict | None) -> tuple[list[tuple[str, str]], list[str]]:
    """Target rows and a worker table from ``mtcw-bench-stream``'s stream.json, read defensively:
    a row without a number the target needs is reported as unreadable, never raises."""
    if not stream:
        return [], []
    rows_in = stream.get("rows") if isinstance(stream, dict) else None
    if not isinstance(rows_in, list):
        return [("streaming", "stream.json has no `rows` list: not reported")], []
    rows = [r for r in rows_in if isinstance(r, dict) and _num(r, "workers") is not None]
    # a run with --threads 1 0 has a row per thread setting: the targets are the deployed one's (1)
    if any(_num(r, "threads") == 1 for r in rows):
        rows = [r for r in rows if _num(r, "threads") == 1]
    scaling = next((sc for sc in stream.get("scaling") or [] if isinstance(sc, dict) and _num(sc, "workers") == 2
                    and _num(sc, "threads") in (1, None)), None)
    targets: list[tuple[str, str]] = []
    one = next((r for r in rows if _num(r, "workers") == 1), None)
    one_fps = _num(one, "throughput", "frames_per_s") if one else None
    table = ["| workers | frames/s (block) | × 1 worker | chain median (ms) | p50 latency (ms) | p99 latency (ms) | "
             "p99/p50 | CPU per published frame (median) |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in sorted(rows, key=lambda r: _num(r, "workers")):
        w = int(_num(r, "workers"))
        fps, ch = _num(r, "throughput", "frames_per_s"), _num(r, "throughput", "chain_median_s")
        p50, p99 = _num(r, "latency_at_80pct", "latency_p50_s"), _num(r, "latency_at_80pct", "latency_p99_s")
        table.append(f"| {w} | {_fmt(fps, '.1f')} | {_fmt(fps / one_fps if fps and one_fps else None, '.2f')} | "
                     f"{_fmt(1e3 * ch if ch else None, '.0f')} | {_fmt(1e3 * p50 if p50 else None, '.0f')} | "
                     f"{_fmt(1e3 * p99 if p99 else None, '.0f')} | {_fmt(p99 / p50 if p50 and p99 else None, '.1f')} | "
                     f"{_cpu_fields(r) or '–'} |")
        if w != 2:
            continue
        if fps is None:
            targets.append(("replay -> 2 workers", "stream.json row for 2 workers has no throughput.frames_per_s"))
            continue
        sr = _num(scaling, "ratio", "ratio") if scaling else None
        if sr is not None:  # the windows' median ratio and its range (mtcw-bench-stream --windows)
            lo, hi, spread = _num(scaling, "ratio", "lo"), _num(scaling, "ratio", "hi"), _num(scaling, "ratio", "spread")
            noisy = bool((scaling.get("ratio") or {}).get("noisy"))
            ok = sr >= STREAM_SCALING
            targets.append((f"replay -> 2 workers ≥ {STREAM_SCALING:g}× one worker's frames/s",
                            f"{sr:.2f}× (windows {_fmt(lo, '.2f')}–{_fmt(hi, '.2f')}, spread "
                            f"{_fmt(100 * spread if spread is not None else None, '.0f')} %{', noisy' if noisy else ''}; "
                            f"{'met' if ok else f'missed: {STREAM_SCALING / sr:.2f}× short'})"))
        elif one_fps:
            x = fps / one_fps
            ok = x >= STREAM_SCALING
            targets.append((f"replay -> 2 workers ≥ {STREAM_SCALING:g}× one worker's frames/s",
                            f"{fps:.1f} / {one_fps:.1f} frames/s = {x:.2f}× "
                            f"({'met' if ok else f'missed: {STREAM_SCALING / x:.2f}× short'})"))
        ch1 = _num(one, "throughput", "chain_median_s") if one else None
        ideal = 2 / ch1 if ch1 else (2 / ch if ch else None)  # two chains at the single-worker chain time
        if ideal:
            f = fps / ideal
            targets.append(("replay -> 2 workers ≥ 80 % of 2 / (chain time)",
                            f"{fps:.1f} frames/s = {100 * f:.0f} % of {ideal:.1f} "
                            f"({'met' if f >= 0.8 else 'missed'}; 2 cores shared by replay, API and both workers)"))
        if p50 and p99:
            q = p99 / p50
            targets.append(("p99 latency < 3× median (2 workers, at 80 % of their rate)",
                            f"{1e3 * p99:.0f} / {1e3 * p50:.0f} ms = {q:.1f}× ({'met' if q < 3 else 'missed'})"))
    if not rows:
        return [("streaming", "stream.json has no row with a `workers` count: not reported")], []
    return targets, table


def _targets(cells: list[dict], refs: dict, sim: list[dict]) -> list[tuple[str, str]]:
    """The benchmark issue's targets, each with what this run measured."""
    rows = []
    bench = [c for c in cells if c["scene"] == "cw-bench"]

    def best(profile: str, method: str = "ml"):
        cs = [c for c in bench if c["profile"] == profile and c["method"] == method and c["time_over_rfft"]]
        return min(cs, key=lambda c: c["loss_db"]) if cs else None

    ml = [c for c in cells if c["method"] == "ml" and c.get("sigma_over_crb") and (c["outlier_rate"] or 0) == 0]
    if ml:
        worst = max(ml, key=lambda c: c["sigma_over_crb"])
        med = sorted(c["sigma_over_crb"] for c in ml)[len(ml) // 2]
        rows.append(("`ml` sigma ≤ 1.2× CRB above threshold",
                     f"median {med:.2f}×, worst {worst['sigma_over_crb']:.2f}× ({worst['scene']}, {worst['loss_db']:g} dB, "
                     f"{worst['profile']})"))
    six = [c for c in cells if c["scene"] == "six-tone"]
    if six:
        def threshold(method: str):
            ok = [c["loss_db"] for c in six if c["method"] == method and c["profile"] == "balanced"
                  and c["outlier_rate"] is not None and c["outlier_rate"] <= 0.1]
            return max(ok) if ok else None
        tm, ts = threshold("ml"), threshold("seed")
        rows.append(("6-tone: `ml` outlier threshold ≥ 3 dB below `seed`'s",
                     f"largest loss with ≤10 % outliers: ml {_fmt(tm, 'g')} dB, seed {_fmt(ts, 'g')} dB"))
    s, b = best("seed", "seed"), best("balanced")
    if s and b:
        ratio = s["median_time_s"] / b["median_time_s"]
        rows.append(("`seed` ≥ 50× slower than `balanced` at no better accuracy",
                     f"{ratio:.0f}× slower; sigma {_fmt(s['range_sigma_m'])} m vs {_fmt(b['range_sigma_m'])} m"))
    if sim and refs:
        n = sim[0]["samples"]
        r = refs.get(str(n), {}).get("rfft_s")
        if r:
            x = sim[0]["sim_s_per_frame"] / r
            rows.append(("simulator: static coherent 3-tone frame ≤ 10× one rfft",
                         f"{x:.1f}× ({'met' if x <= 10 else f'missed by {x / 10:.1f}×'})"))
    return rows


def _plot_stages(cells: list[dict], path: Path) -> None:
    """Stacked bars: median ms per stage (+ unaccounted) per profile, one panel per scene, with
    the cell's float64 rfft as a line (``seed`` left out: 50–150× the others, it flattens them)."""
    scenes = sorted({c["scene"] for c in cells})
    fig, axes = plt.subplots(1, len(scenes), figsize=(3.2 * len(scenes) + 1.8, 4.2), squeeze=False, sharey=True)
    names = [*STAGE_NAMES, UNACCOUNTED]
    colors = plt.get_cmap("tab10")
    for ax, scene in zip(axes[0], scenes):
        profs = [p for p in PROFILES if p != "seed" and target_cell(cells, scene, p)]
        for i, p in enumerate(profs):
            c = target_cell(cells, scene, p)
            bottom = 0.0
            for j, k in enumerate(names):
                v = 1e3 * c["stage_s"].get(k, 0.0)
                ax.bar(i, v, bottom=bottom, color=colors(j), label=k if i == 0 else None, width=0.6)
                bottom += v
            r = c["reference_s"]["fft_f64"]
            ax.hlines(1e3 * r, i - 0.4, i + 0.4, colors="k", linestyles="--", lw=1,
                      label="one float64 rfft" if i == 0 else None)
        ax.set_xticks(range(len(profs)), profs)
        ax.set_title(scene, fontsize=9)
        ax.grid(True, axis="y", alpha=0.3)
    axes[0][0].set_ylabel("median ms per frame")
    h, lab = axes[0][0].get_legend_handles_labels()
    if h:  # top of the stack first, as the bars read
        fig.legend(h[::-1], lab[::-1], fontsize=7, loc="center right")
    fig.tight_layout(rect=(0, 0, 1 - 1.6 / fig.get_figwidth(), 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def stage_table(cells: list[dict], scene: str) -> list[str]:
    """Markdown: median ms per stage per profile for one scene (each with its × float64 rfft), the
    time inside no stage and the total (``process_frame`` as timed from outside)."""
    names = [*STAGE_NAMES, UNACCOUNTED, "total"]
    lines = ["| profile (cell) | " + " | ".join(names) + " |", "| --- |" + " --- |" * len(names)]
    for p in [p for p in PROFILES if target_cell(cells, scene, p)] + sorted(
            {c["profile"] for c in cells if c["scene"] == scene} - set(PROFILES)):
        c = target_cell(cells, scene, p)
        r = c["reference_s"]["fft_f64"]
        st = c["stage_s"]
        vals = [f"{1e3 * st.get(k, 0.0):.2f} ({st.get(k, 0.0) / r:.2f}×)" if st.get(k) else "0" for k in names]
        lines.append(f"| {p} ({c['loss_db']:g} dB, {c['method']}) | " + " | ".join(vals) + " |")
    return lines


def _method_lines(result: dict, refs: dict) -> list[str]:
    noisy = result.get("noisy_spread", NOISY_SPREAD)
    n_dtype = ", ".join(f"{n}: volts {r.get('volts_dtype', '?')}, raw codes {r.get('raw_dtype', '?')}" for n, r in refs.items())
    return [
        "## Method", "",
        "- **Interleaved references.** Every repeat of a cell processes one frame with `process_frame` and, in the same "
        "process, on the same frame, times the references: one pass over the volts (`np.add.reduce`), one `scipy.fft.rfft` "
        "of the volts in float64, in the volts' own dtype (the array the validate stage produces) and of the raw codes as "
        f"stored ({n_dtype}; when the volts are float64 already that transform is timed once and serves both columns). "
        "The order of the five rotates by one from repeat to repeat. Every transform runs on the FFT backend named "
        "under Software, the references' too; with another backend than scipy's own (`--fft-backend pyfftw`) the "
        "float64 rfft is also timed on pocketfft (`scipy.fft.set_backend('scipy', only=True)`), and the targets' "
        "`why` column gives the chain over it: the default install's reference.",
        "- **Ratios per repeat.** A cell's ×rfft is the median over its repeats of (chain time / float64 rfft time of the "
        "same repeat). Its **spread is the interquartile range over the median**, (p75 − p25) / median, of those per-repeat "
        f"ratios; a ratio whose spread exceeds {100 * noisy:.0f} % is marked **noisy** (so is one with fewer than 2 repeats). "
        "The per-stage times are `FrameResult.stage_seconds`; `unaccounted` is the time `process_frame` took minus the sum "
        "of its stages (per repeat, then the median), so it holds the runner's own cost. Medians do not add up exactly.",
        "- **Warm-up.** Before timing, each cell processes two frames under `tracemalloc` (the memory pass below) and one "
        "more untimed (not `seed`, at 1–3 s a frame: its timing follows the memory pass), and runs every reference once. The machine state matters as much as the code: with glibc's allocator "
        "a 1e6-sample rfft takes ~13 ms on memory fresh from the kernel (page faults on the output) and ~7 ms once the heap "
        "has been warmed, and a process running only `fast` can stay in the fresh state; a reference timed apart from the "
        "chain (as earlier reports did, once, on a loaded machine) measures another state, which is why the reference is "
        "timed here in the same state as the chain, interleaved, every repeat.",
        "- **Memory.** Measured in passes of its own (tracemalloc slows numpy's allocation paths, so no time is taken with it "
        "on): a warm-up frame, then the peak of one more frame above what was held just before it, in MB and as a multiple "
        "of the frame's own size in float64 (channels × N × 8 B). Excluded: caches filled on first use and kept afterwards "
        "(windows, Doppler kernels: `lru_cache`s in `mtcw_core`), whose size is what the warm-up frame left held (column "
        "`cache MB` below; 0 when an earlier cell of the same length filled them), the frame itself (its raw codes exist "
        "before the call), and allocations tracemalloc cannot see: pocketfft's C++ scratch buffer (about one transform "
        "length, ≈ N × 8 B for a float64 rfft, transient) and its plan cache.",
        "- **Accuracy** (bias, sigma, outliers against truth and the Cramér–Rao bound) is taken over the first pass through "
        "a cell's frames; timing repeats past the frame count cycle the frames.",
        "- The targets read one cell per scene and profile: the profile's own cycle-resolution method at the lowest echo "
        "loss run (where every frame is ranged; at high losses frames end early as `no_target`, which is cheaper).", ""]


def write_report(result: dict, out: Path, command: str) -> Path:
    """Tables, plots and ``report.md`` under ``out``; returns the report's path."""
    write_tables(result, out)
    cells = result["cells"]
    refs = result["reference_costs"]
    sim = result.get("simulation_costs") or []
    _plot_pareto([c for c in cells if c["scene"] == "cw-bench" and c["loss_db"] == min(
        (d["loss_db"] for d in cells if d["scene"] == "cw-bench"), default=None)] or cells, out / "pareto.png")
    _plot_vs_snr(cells, "range_sigma_m", out / "sigma_vs_snr.png", "range sigma (m)",
                 "range sigma vs SNR, with the Cramér–Rao bound", True, "crb_range_m")
    _plot_vs_snr(cells, "outlier_rate", out / "outliers_vs_snr.png", "outlier (wrong-cycle) rate",
                 "cycle-resolution outliers: seed vs ml", False)
    _plot_stages(cells, out / "stages.png")
    if sim:
        _plot_sim_cost(sim, refs.get(str(sim[0]["samples"]), {}).get("rfft_s"), out / "sim_cost.png")
    m = result.get("machine")
    lines = ["# mtcw benchmark", "", f"Command: `{command}`", ""]
    if isinstance(m, dict):
        lines += [f"Machine: {m.get('cpu')} ({m.get('arch')}), {m.get('cores')} cores ({m.get('usable_cores')} usable), "
                  f"load average {m.get('load_avg')} at the start and {m.get('load_avg_end', '?')} at the end", "",
                  f"Software: Python {m.get('python')}, numpy {m.get('numpy')}, scipy {m.get('scipy')}; FFT backend: "
                  f"{m.get('fft_backend')}, scipy.fft workers {m.get('scipy_fft_workers')}; BLAS/OpenMP threads per pool "
                  f"{m.get('blas_threads')} (a worker's: `MTCW_THREADS`, default 1)", ""]
    else:
        lines += [f"Machine: {m or 'unknown'}", ""]
    if result.get("grid_s"):
        lines += [f"The grid took {result['grid_s'] / 60:.1f} min"
                  + (f"; the whole command {result['total_s'] / 60:.1f} min." if result.get("total_s") else "."), ""]
    speed, mem = speed_target_rows(cells), memory_target_rows(cells)
    stream_targets, stream_table = stream_section(result.get("stream"))
    lines += ["## Targets (issue 16)", "",
              "Speed: the median over repeats of chain time / one float64 rfft of the same frame in the same repeat; "
              "spread = IQR / median of those ratios (see Method).", "",
              "| target | scene | cell | measured (× rfft) | spread | noisy | verdict | why |",
              "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in speed:
        lines.append(f"| {r['target']} | {r['scene']} | {r['cell'] or '–'} | {_fmt(r['median'], '.2f')} | "
                     f"{_pct(r['spread'])} | {'noisy' if r['noisy'] else ('–' if r['noisy'] is None else 'no')} | "
                     f"{r['verdict']} | {r['why']} |")
    lines += ["", "| target | worst cell | peak MB | × frame in float64 | verdict |", "| --- | --- | --- | --- | --- |"]
    lines += [f"| {r['target']} | {r['cell']} | {r['worst_mb']:.1f} | {r['worst_x']:.2f} | {r['verdict']} |" for r in mem]
    other = _targets(cells, refs, sim) + stream_targets
    if other:
        lines += ["", "| other target | measured |", "| --- | --- |"] + [f"| {a} | {b} |" for a, b in other]
    if result.get("stream"):
        cmd = result["stream"].get("command", "mtcw-bench-stream") if isinstance(result["stream"], dict) else "?"
        lines += ["", f"Streaming figures: `{cmd}` (1e6-sample frames replayed through acquisition -> workers -> API on "
                      "loopback; from its stream.json, not measured by this command).", ""] + stream_table
    lines += [""] + _method_lines(result, refs)
    lines += ["## Reference costs (interleaved with the chain; median over the cells of each length)", "",
              "| samples | one pass (ms) | rfft float64 (ms) | rfft volts' dtype (ms) | rfft raw codes (ms) | "
              "spread of the float64 rfft over cells |", "| --- | --- | --- | --- | --- | --- |"]
    for n, r in refs.items():
        lines.append(f"| {n} | {1e3 * r['pass_s']:.2f} | {1e3 * r.get('fft_f64_s', r['rfft_s']):.2f} | "
                     f"{_fmt(1e3 * r['fft_volts_s'] if r.get('fft_volts_s') else None, '.2f')} ({r.get('volts_dtype', '?')}) | "
                     f"{_fmt(1e3 * r['fft_raw_s'] if r.get('fft_raw_s') else None, '.2f')} ({r.get('raw_dtype', '?')}) | "
                     f"{_pct(r.get('fft_f64_spread'))} |")
    lines += ["", "## Where the time goes: median ms per stage (× the cell's float64 rfft)", "",
              "Each stage's median over the cell's repeats, over the median of the cell's float64 rfft (the targets' "
              "ratio is the median of the per-repeat ratios, so its total may differ a little); `unaccounted` is the "
              "time inside `process_frame` outside every stage. The figure leaves `seed` out (50–150× the others).", "",
              "![stages](stages.png)", ""]
    for scene in sorted({c["scene"] for c in cells}):
        lines += [f"### {scene}", ""] + stage_table(cells, scene) + [""]
    lines += ["## Peak memory per frame", "",
              "| scene | profile (cell) | peak MB | × frame in float64 | cache MB (held after the warm-up frame) |",
              "| --- | --- | --- | --- | --- |"]
    for scene in sorted({c["scene"] for c in cells}):
        for p in PROFILES:
            c = target_cell(cells, scene, p)
            if c is not None and c.get("peak_memory_x_f64") is not None:
                lines.append(f"| {scene} | {p} ({c['loss_db']:g} dB, {c['method']}) | {c['peak_memory_mb']:.1f} | "
                             f"{c['peak_memory_x_f64']:.2f} | {c.get('warmup_retained_mb', 0):.1f} |")
    held = [c for c in cells if c.get("warmup_retained_mb") is not None]
    if held:
        big = max(held, key=lambda c: c["warmup_retained_mb"])
        lines += ["", f"Memory held after warm-up frames, summed over the run's {len(held)} cells (caches filled on first "
                      f"use, e.g. windows): {sum(c['warmup_retained_mb'] for c in held):.1f} MB; the largest single: "
                      f"{big['warmup_retained_mb']:.1f} MB ({big['scene']}, {big['profile']}/{big['method']}, first cell "
                      "of its kind)."]
    lines += ["", "## Reading the bound", "",
              "The Cramér–Rao bound here is computed from the truth with white (shot + thermal) noise only. "
              "At high SNR on coherent scenes the laser's phase-noise skirts and the modulator's products, not "
              "shot noise, set the floor, so sigma/CRB grows with SNR; for the 5.3 GHz-linewidth scene the "
              "LO x echo beat spread over the band is a noise the bound leaves out, so its ratio is not "
              "meaningful. The `seed` method takes the finest pair's range (the candidate-matrix column 1), "
              "which is why its sigma is worse on the 6-tone plan."]
    lines += ["", "## Figures", "", "![Pareto](pareto.png)", "", "![sigma vs SNR](sigma_vs_snr.png)", "",
              "![outliers](outliers_vs_snr.png)", ""]
    if sim:
        lines += ["![simulation cost](sim_cost.png)", ""]
    lines += ["## All cells", "",
              "| scene | loss dB | profile | method | ms/frame | ×rfft | spread | bias (m) | sigma (m) | CRB (m) | "
              "sigma/CRB | outliers | speed sigma (m/s) | peak MB | peak × f64 |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for c in cells:
        lines.append(
            f"| {c['scene']} | {c['loss_db']:g} | {c['profile']} | {c['method']} | "
            f"{_fmt(1e3 * c['median_time_s'] if c['median_time_s'] else None, '.1f')} "
            f"| {_fmt(c.get('time_over_rfft'), '.2f')}{' (noisy)' if c.get('ratio_noisy') else ''} | "
            f"{_pct(c.get('ratio_spread'))} | {_fmt(c['range_bias_m'], '.2e')} | {_fmt(c['range_sigma_m'], '.2e')} "
            f"| {_fmt(c.get('crb_range_m'), '.2e')} | {_fmt(c.get('sigma_over_crb'), '.2f')} | {_fmt(c['outlier_rate'], '.2f')} "
            f"| {_fmt(c['speed_sigma_mps'], '.2e')} | {c['peak_memory_mb']:.0f} | {_fmt(c.get('peak_memory_x_f64'), '.2f')} |")
    if sim:
        lines += ["", "## Simulator cost vs scene complexity", "", "| scene | ms/frame |", "| --- | --- |"]
        lines += [f"| {s['scene']} | {1e3 * s['sim_s_per_frame']:.1f} |" for s in sim]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


__all__ = ["write_report", "write_tables", "speed_target_rows", "memory_target_rows", "stream_section", "stage_table",
           "target_cell", "verdict", "SPEED_TARGETS", "MEMORY_LIMIT_X_F64", "MEMORY_EXEMPT", "STREAM_SCALING"]
