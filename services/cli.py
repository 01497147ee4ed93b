"""``mtcw``: one entry point, subcommands. Thin: parses settings and calls mtcw_core."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Optional

import typer
from tqdm import tqdm

from mtcw_core.recording import RecordingError, RecordingWriter, read_recording
from mtcw_core.scene import SceneError, bundled_scenes, load_scene
from mtcw_core.simulate import Simulator

app = typer.Typer(add_completion=False, no_args_is_help=True, help="Multi-tone CW lidar: simulate, process, serve.")


def _fail(msg: str, code: int = 2) -> None:
    typer.secho(f"error: {msg}", err=True, fg=typer.colors.RED)
    raise typer.Exit(code)


@app.command()
def scenes() -> None:
    """List the example scenes shipped with mtcw."""
    for name, path in sorted(bundled_scenes().items()):
        sc = load_scene(path)
        typer.echo(f"{name:24s} {sc.description}")


@app.command()
def simulate(
    scene: str = typer.Argument(..., help="scene file (TOML/JSON) or bundled scene name"),
    output: Path = typer.Option(..., "-o", "--output", help="recording prefix (writes PREFIX.sigmf-meta/-data)"),
    frames: Optional[int] = typer.Option(None, "--frames", "-n", help="number of frames (default: the scene's)"),
    seed: Optional[int] = typer.Option(None, help="RNG seed (default: the scene's)"),
    samples: Optional[int] = typer.Option(None, help="override samples per frame"),
) -> None:
    """Simulate a scene and write the frames as a SigMF recording (with truth)."""
    try:
        sc = load_scene(scene)
        if samples is not None:
            sc = sc.model_validate({**sc.model_dump(), "digitizer": {**sc.digitizer.model_dump(), "samples": samples}})
    except (SceneError, ValueError) as err:
        _fail(str(err))
    sim = Simulator(sc, seed)
    count = sc.frames.count if frames is None else frames
    t0 = time.perf_counter()
    try:
        with RecordingWriter(output, description=f"mtcw simulation of scene {sc.name}: {sc.description}") as w:
            for fr in tqdm(sim.frames(count), total=count, unit="frame", desc=f"simulate {sc.name}", file=sys.stderr):
                w.write(fr)
    except RecordingError as err:
        _fail(str(err))
    dt = time.perf_counter() - t0
    typer.echo(f"wrote {count} frames of {sc.digitizer.samples} samples to {w.meta_path} "
               f"({dt / count * 1e3:.1f} ms/frame)")


@app.command()
def info(recording: Path = typer.Argument(..., help="SigMF recording (prefix or .sigmf-meta)")) -> None:
    """Summarise a SigMF recording."""
    try:
        rec = read_recording(recording)
    except RecordingError as err:
        _fail(str(err))
    g = rec.glob
    out = {
        "frames": len(rec),
        "frame_samples": rec.frame_samples,
        "datatype": g["core:datatype"],
        "sample_rate_hz": g["core:sample_rate"],
        "tones_hz": g["mtcw:tones_hz"],
        "receiver": rec.receiver,
        "channels": list(rec.channels),
        "truth_first_frame": rec.meta["captures"][0].get("mtcw:truth"),
    }
    typer.echo(json.dumps(out, indent=2))


def _open(recording: Path):
    try:
        return read_recording(recording)
    except RecordingError as err:
        _fail(str(err))


def _settings(profile: str, method: Optional[str]):
    from mtcw_core.chain import get_profile

    try:
        return get_profile(profile, **({"method": method} if method else {}))
    except ValueError as err:
        _fail(str(err))


def _point_rows(res) -> list[dict]:
    base = {"seq": res.seq, "t_ns": res.t_ns, "source": res.source, "status": res.status, "reason": res.reason,
            "profile": res.profile, "unambiguous_range_m": res.unambiguous_range_m}
    if not res.targets:
        return [base]
    return [{**base, **{k: v for k, v in vars(t).items() if k != "tone_snr_db"}} for t in res.targets]


@app.command()
def process(
    recording: Path = typer.Argument(..., help="SigMF recording"),
    output: Optional[Path] = typer.Option(None, "-o", "--output", help="points.csv or points.json"),
    profile: str = typer.Option("balanced", help="fast | balanced | accurate | seed"),
    method: Optional[str] = typer.Option(None, help="override cycle resolution: ml | seed"),
    calibration: Optional[Path] = typer.Option(None, help="calibration file from `mtcw calibrate`"),
) -> None:
    """Run the PB-MTCW chain on every frame of a recording: one point per frame and target."""
    import csv

    import numpy as np

    from mtcw_core.calibration import Calibration, CalibrationError
    from mtcw_core.chain import process_frame

    rec = _open(recording)
    settings = _settings(profile, method)
    cal = None
    if calibration is not None:
        try:
            cal = Calibration.load(calibration)
        except CalibrationError as err:
            _fail(str(err))
    else:
        typer.secho("no calibration: using the recording's tone phases (mtcw:tone_phases_rad, else 0) and tau0 = 0",
                    err=True, fg=typer.colors.YELLOW)
    rows, errs, times, status = [], [], [], {}
    for fr in tqdm(rec, total=len(rec), unit="frame", desc=f"process [{settings.profile}]", file=sys.stderr):
        res = process_frame(fr, settings, cal)
        status[res.status] = status.get(res.status, 0) + 1
        times.append(sum(res.stage_seconds.values()))
        rows += _point_rows(res)
        if fr.truth and res.targets:
            t, p = fr.truth[0], res.targets[0]
            errs.append((p.range_m - t.range_m, p.range_sigma_m, abs(p.velocity_mps) - abs(t.velocity_mps)))
    if output is not None:
        if output.suffix == ".json":
            output.write_text(json.dumps(rows, indent=1, default=float))
        else:
            keys = sorted({k for r in rows for k in r})
            with open(output, "w", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=keys)
                w.writeheader()
                w.writerows(rows)
    summary = {"frames": len(rec), "status": status, "median_ms_per_frame": 1e3 * float(np.median(times))}
    if errs:
        e = np.asarray(errs)
        summary.update({
            "range_bias_m": float(np.mean(e[:, 0])), "range_std_m": float(np.std(e[:, 0])),
            "median_reported_sigma_m": float(np.median(e[:, 1])),
            "max_abs_range_error_m": float(np.max(np.abs(e[:, 0]))),
            "speed_bias_mps": float(np.mean(e[:, 2])),
        })
    typer.echo(json.dumps(summary, indent=2))


@app.command()
def calibrate(
    recording: Path = typer.Argument(..., help="SigMF recording of a reflector at a known range"),
    known_range: float = typer.Option(..., "--known-range", help="range of the reflector (m)"),
    output: Path = typer.Option(Path("calibration.json"), "-o", "--output"),
) -> None:
    """Derive tone phase offsets and tau0 from a known reflector; write a calibration file."""
    from mtcw_core.calibration import CalibrationError, derive_calibration
    from mtcw_core.chain import Rejected

    rec = _open(recording)
    try:
        cal = derive_calibration(tqdm(rec, total=len(rec), unit="frame", desc="calibrate", file=sys.stderr),
                                 known_range, source=str(recording))
    except (CalibrationError, Rejected) as err:
        _fail(str(err))
    cal.save(output)
    typer.echo(json.dumps({"written": str(output), "tau0_s": cal.tau0_s, "tone_phases_rad": cal.tone_phases_rad,
                           "phase_std_rad": cal.phase_std_rad, "frames": cal.frames_used}, indent=2))


@app.command()
def run(
    scene: str = typer.Option("cw-bench", help="scene file or bundled scene name"),
    profile: str = typer.Option("balanced"),
    frames: int = typer.Option(0, help="stop after this many frames (0 = run until Ctrl-C)"),
) -> None:
    """All-in-one on a simulated bench. Interim form: simulate and process in one process and print points.

    The streaming services (acquisition node, workers, HTTP API) are not built yet; see README.
    """
    from mtcw_core.chain import process_frame

    try:
        sc = load_scene(scene)
    except SceneError as err:
        _fail(str(err))
    settings = _settings(profile, None)
    sim = Simulator(sc)
    typer.echo(f"mtcw run: scene {sc.name} ({sc.description}), profile {settings.profile}; Ctrl-C to stop")
    i = 0
    try:
        while frames == 0 or i < frames:
            fr = sim.next_frame()
            res = process_frame(fr, settings)
            t = fr.truth[0]
            if res.targets:
                p = res.targets[0]
                typer.echo(f"seq {res.seq:5d}  range {p.range_m:10.6f} m +- {p.range_sigma_m:.1e}  "
                           f"(truth {t.range_m:.6f})  speed {p.velocity_mps:+.4f} m/s {p.direction:8s} "
                           f"chain {1e3 * sum(res.stage_seconds.values()):6.1f} ms")
            else:
                typer.echo(f"seq {res.seq:5d}  {res.status}: {res.reason}")
            i += 1
    except KeyboardInterrupt:
        typer.echo("stopped")


def main() -> None:
    app()


if __name__ == "__main__":
    main()
