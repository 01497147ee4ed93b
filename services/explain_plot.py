"""PNG figures of :func:`mtcw_core.explain.explain_frame`'s data (matplotlib, Agg): ``mtcw explain``.

Three figures per frame, after the dissertation's: the spectrum with every line marked (Figs. 21,
23, 27), the cycle-resolution cost J(L) with the chosen peak and the runner-up (Fig. 28), the
seed's candidate matrix and its sigma_k curve (Fig. 18). Plotting lives here, not in
``mtcw_core`` (no matplotlib in the core).
"""

from __future__ import annotations

import json
from pathlib import Path

#: marker colour and label of each kind of line
STYLE = {
    "tone": ("tab:blue", "static line f_i (S)"),
    "doppler_upper": ("tab:green", "Doppler line f_i + f_d (U)"),
    "doppler_lower": ("tab:olive", "Doppler line |f_i - f_d| (L)"),
    "doppler": ("tab:red", "baseband Doppler |f_d|"),
    "product": ("tab:gray", "tone product (left out)"),
    "ghost": ("tab:purple", "ghost: product shifted by f_d (left out)"),
}


def _mhz(v):
    return [x / 1e6 for x in v]


def plot_spectrum(d: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    sp = d["spectrum"]
    fig, ax = plt.subplots(figsize=(11, 4.2), dpi=110)
    ax.plot(_mhz(sp["f_hz"]), sp["power_db"], lw=0.6, color="0.35")
    top = max(sp["power_db"]) if sp["power_db"] else 0.0
    shown = set()
    for ln in d["lines"]:
        colour, label = STYLE.get(ln["kind"], ("k", ln["kind"]))
        used = ln["used"]
        ax.axvline(ln["f_hz"] / 1e6, color=colour, lw=1.0 if used else 0.8, ls="-" if used else ":", alpha=0.8,
                   label=None if (ln["kind"], used) in shown else label + ("" if used or ln["kind"] in (
                       "product", "ghost") else " - not used"))
        shown.add((ln["kind"], used))
    ax.set_xlabel("frequency (MHz)")
    ax.set_ylabel("power over the mean noise floor (dB)")
    ax.set_ylim(-15, top + 8)
    ax.set_xlim(min(sp["f_hz"]) / 1e6, max(sp["f_hz"]) / 1e6)
    ax.set_title(f"{d['source']} seq {d['seq']}: search spectrum ({sp['bins']} bins of {sp['df_hz'] / 1e3:.1f} kHz, "
                 f"max per display point), lines the chain used and left out")
    ax.legend(loc="upper right", fontsize=7, ncol=2)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _truth_marks(ax, d: dict, cand: dict) -> None:
    """Truth ranges, folded into the searched interval (the phases see range modulo the unambiguous range)."""
    lo, hi = cand["cost"]["interval_m"]
    period = cand["cost"]["unambiguous_range_m"]
    for i, t in enumerate(d.get("truth") or ()):
        r = t["range_m"]
        if period:
            r = lo + (r - lo) % period
        if lo <= r <= hi:
            ax.axvline(r, color="tab:green", lw=1.0, ls="--", label="truth (folded)" if i == 0 else None)


def plot_cost(d: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    cands = d["candidates"]
    fig, axes = plt.subplots(len(cands), 1, figsize=(11, 3.2 * len(cands)), dpi=110, squeeze=False)
    for ax, c in zip(axes[:, 0], cands):
        cost = c["cost"]
        ax.plot(cost["range_m"], cost["j"], lw=0.8, color="0.25", label="J(L)")
        ax.plot([cost["chosen_m"]], [cost["j_chosen"]], "o", color="tab:red",
                label=f"chosen {cost['chosen_m']:.6g} m (J = {cost['j_chosen']:.3f})")
        if cost["runner_up_m"] is not None:
            ax.plot([cost["runner_up_m"]], [cost["j_runner_up"]], "s", color="tab:orange",
                    label=f"runner-up {cost['runner_up_m']:.6g} m (J = {cost['j_runner_up']:.3f}); "
                          f"margin {cost['margin']:.3f}")
        _truth_marks(ax, d, c)
        kind = "static" if c["candidate"] == 0 else f"Doppler {c['doppler_hz'] / 1e6:.3f} MHz"
        ax.set_title(f"candidate {c['candidate']} ({kind}){'' if c['reported'] else ', not reported'}: "
                     f"cycle-resolution cost over the searched interval", fontsize=9)
        ax.set_xlabel("range L (m)")
        ax.set_ylabel("J(L)")
        ax.set_ylim(-1.05, 1.1)
        ax.legend(loc="lower right", fontsize=7)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_seed(d: dict, path: Path) -> None:
    import matplotlib.pyplot as plt
    import numpy as np

    cands = d["candidates"]
    fig, axes = plt.subplots(len(cands), 2, figsize=(11, 3.4 * len(cands)), dpi=110, squeeze=False)
    for (ax_m, ax_s), c in zip(axes, cands):
        sd = c["seed"]
        m = np.asarray(sd["candidates_m"])
        rows = sd["first_row"] + np.arange(m.shape[0])
        for j in range(m.shape[1]):
            ax_m.plot(m[:, j], rows, ".", ms=4, label=f"Lambda = {sd['synthetic_wavelengths_m'][j]:.3g} m")
        ax_m.axhline(sd["chosen_row"], color="tab:red", lw=0.8, label=f"chosen row (sigma_k {sd['sigma_k_chosen_m']:.2e} m)")
        ax_m.set_xlabel("candidate range (m)")
        ax_m.set_ylabel("row k")
        ax_m.set_title(f"candidate {c['candidate']}: the seed's candidate matrix (one column per pair)", fontsize=9)
        ax_m.legend(fontsize=6, loc="upper left")
        ax_m.grid(alpha=0.3)
        ax_s.semilogy(sd["curve_range_m"], np.maximum(sd["curve_sigma_k_m"], 1e-12), ".-", lw=0.6, ms=3)
        ax_s.plot([sd["chosen_m"]], [max(sd["sigma_k_chosen_m"], 1e-12)], "o", color="tab:red",
                  label=f"min at {sd['chosen_m']:.6g} m")
        _truth_marks(ax_s, d, c)
        ax_s.set_xlabel("column-1 range of row k (m)")
        ax_s.set_ylabel("sigma_k (m)")
        ax_s.set_title("row standard deviation sigma_k", fontsize=9)
        ax_s.legend(fontsize=7)
        ax_s.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def write_explain(d: dict, out_dir: Path) -> list[Path]:
    """``explain.json`` and, when the chain got that far, ``spectrum.png``, ``cost.png`` and
    ``seed.png`` in ``out_dir`` (created); returns the paths written."""
    import matplotlib

    matplotlib.use("Agg")
    out_dir.mkdir(parents=True, exist_ok=True)
    written = [out_dir / "explain.json"]
    written[0].write_text(json.dumps(d, indent=1))
    if d.get("spectrum"):
        plot_spectrum(d, out_dir / "spectrum.png")
        written.append(out_dir / "spectrum.png")
    if d.get("candidates"):
        plot_cost(d, out_dir / "cost.png")
        plot_seed(d, out_dir / "seed.png")
        written += [out_dir / "cost.png", out_dir / "seed.png"]
    return written
