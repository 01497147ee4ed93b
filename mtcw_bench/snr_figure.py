"""``mtcw snr``: SNR against echo attenuation (the dissertation's Fig. 36) as a table and a PNG.

The numbers come from :class:`mtcw_core.snr.Link` (pure); this module only tabulates and draws
them (matplotlib stays out of ``mtcw_core``).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mtcw_core.snr import Link  # noqa: E402


def _label(bw_hz: float) -> str:
    return f"{bw_hz / 1e6:g} MHz"


def crossing_db(att_db: np.ndarray, snr_db: np.ndarray, level_db: float) -> float | None:
    """The attenuation (dB) at which a falling SNR curve crosses ``level_db`` (linear interpolation)."""
    below = np.flatnonzero(snr_db < level_db)
    if below.size == 0 or below[0] == 0:
        return None
    k = below[0]
    a0, a1, s0, s1 = att_db[k - 1], att_db[k], snr_db[k - 1], snr_db[k]
    return float(a0 + (s0 - level_db) * (a1 - a0) / (s0 - s1))


def snr_curves(link: Link, bandwidths_hz: list[float], max_attenuation_db: float = 120.0,
               step_db: float = 1.0) -> dict:
    """Every curve of the figure: the model, the dissertation's Eq. (5.11) as printed, the dominant
    noise term, and where each curve crosses 0 dB and 20 dB.

    Returns
    -------
    dict with ``attenuation_db`` (list), per bandwidth label ``model_db``, ``eq_5_11_db``,
    ``dominant`` (list of term names) and ``crossings`` ({"0 dB": att, "20 dB": att})
    """
    att = np.arange(0.0, max_attenuation_db + step_db / 2, step_db)
    out: dict = {"attenuation_db": att.tolist(), "link": {k: getattr(link, k) for k in link.__dataclass_fields__},
                 "curves": {}}
    for bw in bandwidths_hz:
        t = link.terms(att, bw)
        model = np.asarray(t.snr_db, float)
        diss = 10 * np.log10(np.asarray(link.dissertation(att, bw), float))
        names = list(t.terms_a2())
        stack = np.stack([np.broadcast_to(v, att.shape) for v in t.terms_a2().values()])
        out["curves"][_label(bw)] = {
            "bandwidth_hz": bw, "model_db": model.tolist(), "eq_5_11_db": diss.tolist(),
            "dominant": [names[i] for i in np.argmax(stack, axis=0)],
            "crossings_model": {f"{lv:g} dB": crossing_db(att, model, lv) for lv in (20.0, 0.0)},
            "crossings_eq_5_11": {f"{lv:g} dB": crossing_db(att, diss, lv) for lv in (20.0, 0.0)},
        }
    return out


def write_snr(link: Link, out: Path, bandwidths_hz: list[float], max_attenuation_db: float = 120.0,
              step_db: float = 1.0) -> dict:
    """Write ``snr.csv``, ``snr.json`` and ``snr.png`` under ``out``; return the curves."""
    out.mkdir(parents=True, exist_ok=True)
    res = snr_curves(link, bandwidths_hz, max_attenuation_db, step_db)
    att = res["attenuation_db"]
    labels = list(res["curves"])
    with open(out / "snr.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["attenuation_db"] + [f"snr_db_{lb.replace(' ', '')}" for lb in labels]
                   + [f"eq_5_11_db_{lb.replace(' ', '')}" for lb in labels] + ["dominant_noise"])
        for k, a in enumerate(att):
            w.writerow([f"{a:g}"] + [f"{res['curves'][lb]['model_db'][k]:.2f}" for lb in labels]
                       + [f"{res['curves'][lb]['eq_5_11_db'][k]:.2f}" for lb in labels]
                       + [res["curves"][labels[0]]["dominant"][k]])
    (out / "snr.json").write_text(json.dumps(res, indent=1) + "\n")
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for i, lb in enumerate(labels):
        c = f"C{i}"
        ax.plot(att, res["curves"][lb]["model_db"], color=c, label=f"{lb} (model)")
        ax.plot(att, res["curves"][lb]["eq_5_11_db"], color=c, ls=":", label=f"{lb} (Eq. 5.11 as printed)")
    ax.axhline(0.0, color="r", ls="--", lw=1)
    ax.axhline(20.0, color="b", ls="--", lw=1)
    ax.set_xlabel("echo attenuation (dB)")
    ax.set_ylabel("line SNR (dB)")
    ax.set_title(f"SNR vs attenuation: P_LO {link.p_lo_w * 1e3:g} mW, echo {link.p_echo_w * 1e3:g} mW, "
                 f"G {link.gain_db:g} dB, {link.receiver}", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "snr.png", dpi=110)
    plt.close(fig)
    return res
