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
from mtcw_core.scene import SceneError, bundled_scenes, load_scene, scene_variant
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
            sc = scene_variant(sc, digitizer={"samples": samples})
    except (SceneError, ValueError) as err:
        _fail(str(err))
    sim = Simulator(sc, seed)
    count = sc.frames.count if frames is None else frames
    t0 = time.perf_counter()
    try:
        with RecordingWriter(output, description=f"mtcw simulation of scene {sc.name}: {sc.description}") as w:
            for fr in tqdm(sim.frames(count), total=count, unit="frame", desc=f"simulate {sc.name}", file=sys.stderr):
                w.write(fr)
    except (RecordingError, SceneError) as err:  # a target reaching the sensor ends the scene
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
    g, truth = rec.meta.global_info, rec.meta.captures[0].truth
    out = {
        "frames": len(rec),
        "frame_samples": rec.frame_samples,
        "datatype": g.datatype,
        "sample_rate_hz": g.sample_rate,
        "tones_hz": g.tones_hz,
        "receiver": rec.receiver,
        "channels": list(rec.channels),
        "truth_first_frame": None if truth is None else [t.model_dump() for t in truth],
    }
    typer.echo(json.dumps(out, indent=2))


def _open(recording: Path):
    try:
        return read_recording(recording)
    except RecordingError as err:
        _fail(str(err))


def _settings(profile: str, method: Optional[str], technique: str = "pb", timing_jitter_s: float = 0.0,
              laser_linewidth_hz: float = 0.0, lo_path_difference_m: float = 0.0, sideband_direction: bool = False,
              tone_phase_sigma_rad: float = 0.0):
    from mtcw_core.chain import get_profile

    over = {"method": method} if method else {}
    if technique != "pb":
        over["technique"] = technique
    if timing_jitter_s:
        over["timing_jitter_s"] = timing_jitter_s
    if tone_phase_sigma_rad:
        over["tone_phase_sigma_rad"] = tone_phase_sigma_rad
    if laser_linewidth_hz or lo_path_difference_m:
        over.update(laser_linewidth_hz=laser_linewidth_hz, lo_path_difference_m=lo_path_difference_m)
    if sideband_direction:
        over["sideband_direction"] = True
    try:
        return get_profile(profile, **over)
    except ValueError as err:
        _fail(str(err))


def _accumulator(frames: int, settings, calibration: Optional[Path]):
    """``--accumulate K``: an :class:`~mtcw_core.ranging.accumulate.Accumulator` (None for 0); a bad K
    or technique ends the command naming the option."""
    if not frames:
        return None
    from pydantic import ValidationError

    from mtcw_core.ranging.accumulate import AccumulateSettings, Accumulator

    try:
        return Accumulator(AccumulateSettings(frames=frames), settings, _calibration(calibration))
    except ValidationError as err:
        _fail(f"--accumulate: {err.errors()[0]['msg']} (got {frames})")
    except ValueError as err:
        _fail(f"--accumulate: {err}")


def _tracker(frames: int, max_speed_mps: Optional[float]):
    """``--track K``: a :class:`~mtcw_core.ranging.track.Tracker` over windows of K points (None for 0);
    a bad K or speed ends the command naming the option."""
    if not frames:
        return None
    from pydantic import ValidationError

    from mtcw_core.ranging.track import Tracker, TrackSettings

    try:
        return Tracker(TrackSettings(frames=frames, max_speed_mps=max_speed_mps))
    except ValidationError as err:
        e = err.errors()[0]
        name = "--track-max-speed" if "max_speed" in str(e.get("loc")) else "--track"
        _fail(f"{name}: {e['msg']} (got {max_speed_mps if name != '--track' else frames})")


TONE_PHASE_HELP = ("the RF synthesizers' known rms phase drift per tone since calibration (rad); enters every "
                   "range sigma and the line phases' consistency")
TRACK_HELP = ("range rate over frames: each target's ranges over its last K frames (3-64; 0: off), "
              "a speed where the laser is incoherent and the direction on one photodiode (range_rate_mps)")
TRACK_SPEED_HELP = ("with --track: the fastest range rate a target may have (m/s; default: each point's own "
                    "bound, its Doppler speed or the search's largest: a laser incoherent at the target needs it)")


def _calibration(path: Optional[Path]):
    """The calibration file at ``path`` (None: none); a bad file ends the command naming it."""
    from mtcw_core.calibration import Calibration, CalibrationError

    if path is None:
        return None
    try:
        return Calibration.load(path)
    except CalibrationError as err:
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
    technique: str = typer.Option("pb", help="pb (phase-based MTCW) | ab | pe | ptof"),
    timing_jitter_s: float = typer.Option(0.0, "--timing-jitter-s", help="the digitizer's known rms timing jitter "
                                                                         "(s); enters every range sigma"),
    tone_phase_sigma_rad: float = typer.Option(0.0, "--tone-phase-sigma-rad", help=TONE_PHASE_HELP),
    laser_linewidth_hz: float = typer.Option(0.0, "--laser-linewidth-hz", help="the bench's laser (Lorentzian FWHM, "
                                             "Hz): where it is incoherent at the echo's delay a speed is unknown, "
                                             "not 0, and the square stage ranges from the squared record "
                                             "(docs/reach.md); 0: coherent everywhere"),
    lo_path_difference_m: float = typer.Option(0.0, "--lo-path-difference-m", help="optical path of the LO minus "
                                               "the echo's internal path (m), with --laser-linewidth-hz"),
    accumulate: int = typer.Option(0, "--accumulate", help="beyond the laser's coherence (a static target): range "
                                   "from the whole band's digital IF mixing, averaged over the last K frames "
                                   "(1-32; 0: the chain per frame); docs/reach.md"),
    sideband_direction: bool = typer.Option(False, "--sideband-direction", help="one photodiode: say the direction "
                                            "of motion where the sidebands' own Doppler shift decides its sign (high "
                                            "SNR; off: direction unknown, as the interface says)"),
    track: int = typer.Option(0, "--track", help=TRACK_HELP),
    track_max_speed: Optional[float] = typer.Option(None, "--track-max-speed", help=TRACK_SPEED_HELP),
) -> None:
    """Run the chain of a technique (PB-MTCW by default) on every frame of a recording: one point per frame and
    target."""
    import csv

    import numpy as np

    from mtcw_core.chain import process_frame
    from mtcw_core.evaluate import ErrorLog

    rec = _open(recording)
    settings = _settings(profile, method, technique, timing_jitter_s, laser_linewidth_hz, lo_path_difference_m,
                         sideband_direction, tone_phase_sigma_rad)
    acc = _accumulator(accumulate, settings, calibration)
    tracker = _tracker(track, track_max_speed)
    cal = _calibration(calibration)
    if cal is None:
        typer.secho("no calibration: using the recording's tone phases (mtcw:tone_phases_rad, else 0) and tau0 = 0",
                    err=True, fg=typer.colors.YELLOW)
    rows, times, stages, status, log = [], [], {}, {}, ErrorLog()
    truths: dict[int, tuple] = {}  # seq -> truth, for the frames an accumulated point rests on
    try:
        for fr in tqdm(rec, total=len(rec), unit="frame", desc=f"process [{settings.profile}]", file=sys.stderr):
            if acc is None:
                res, truth = process_frame(fr, settings, cal), fr.truth or ()
            else:
                from mtcw_core.ranging.accumulate import mean_truth

                res = acc.add(fr)
                truths[fr.seq] = fr.truth or ()
                truth = mean_truth([truths[s] for s in acc.window_seqs() if s in truths])
                truths = {s: truths[s] for s in acc.window_seqs() if s in truths}
            if tracker is not None:
                res = tracker.update(res)
            status[res.status] = status.get(res.status, 0) + 1
            times.append(sum(res.stage_seconds.values()))
            for name, sec in res.stage_seconds.items():
                stages.setdefault(name, []).append(sec)
            rows += _point_rows(res)
            for t in truth:
                log.add(res, t)
    except RecordingError as err:  # the data file changed under us after it was opened
        _fail(str(err))
    if output is not None:
        if output.suffix == ".json":
            output.write_text(json.dumps(rows, indent=1, default=float))
        else:
            keys = sorted({k for r in rows for k in r})
            with open(output, "w", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=keys)
                w.writeheader()
                w.writerows(rows)
    summary = {"frames": len(rec), "status": status, "median_ms_per_frame": 1e3 * float(np.median(times)),
               "median_ms_per_stage": {k: round(1e3 * float(np.median(v)), 3) for k, v in stages.items()}}
    if acc is not None:  # truth of an accumulated point: the mean over the frames it rests on
        summary["accumulate"] = {"frames": accumulate, "new_windows": dict(acc.resets)}
    if tracker is not None:
        summary["track"] = {"frames": track, "ended": dict(tracker.ends), "restarts": tracker.restarts,
                            "withheld_disagreeing_with_doppler": tracker.disagree,
                            "steps_of_unknown_cycle": tracker.ambiguous}
    if log.range_error_m:
        summary.update(log.summary())
    typer.echo(json.dumps(summary, indent=2))


@app.command()
def explain(
    recording: Path = typer.Argument(..., help="SigMF recording"),
    frame: int = typer.Option(0, "--frame", "-k", help="frame index (negative counts from the end)"),
    output: Path = typer.Option(Path("out/explain"), "-o", "--output", help="directory for the PNGs and explain.json"),
    profile: str = typer.Option("balanced", help="fast | balanced | accurate | seed"),
    method: Optional[str] = typer.Option(None, help="override cycle resolution: ml | seed"),
    calibration: Optional[Path] = typer.Option(None, help="calibration file from `mtcw calibrate`"),
) -> None:
    """One frame's triangulation made visible: spectrum with every line marked, J(L) with the chosen
    peak and the runner-up, the seed's candidate matrix and sigma_k (PNGs and explain.json)."""
    from mtcw_core.explain import explain_frame
    from services.explain_plot import write_explain

    rec = _open(recording)
    settings = _settings(profile, method)
    try:
        fr = rec.frame(frame)
    except IndexError as err:
        _fail(f"--frame: {err}")
    except RecordingError as err:
        _fail(str(err))
    d = explain_frame(fr, settings, _calibration(calibration))
    written = write_explain(d, output)
    summary = {"frame": frame, "seq": d["seq"], "status": d["status"], "reason": d["reason"],
               "targets": [{"range_m": t["range_m"], "range_sigma_m": t["range_sigma_m"], "margin": t["margin"]}
                           for t in d["targets"]],
               "truth": d["truth"], "written": [str(p) for p in written]}
    typer.echo(json.dumps(summary, indent=2))


@app.command()
def calibrate(
    recording: Path = typer.Argument(..., help="SigMF recording of a reflector at a known range"),
    known_range: float = typer.Option(..., "--known-range", help="range of the reflector (m); with --technique ab "
                                                                  "the reference mirror's"),
    output: Path = typer.Option(Path("calibration.json"), "-o", "--output"),
    technique: str = typer.Option("pb", help="pb: tone phases and tau0 from a known reflector; ab: the reference "
                                             "arm's tone powers from a reference-only recording"),
) -> None:
    """Derive tone phase offsets and tau0 from a known reflector (or, ``--technique ab``, the reference arm's tone
    powers from a recording without the measurement arm); write a calibration file."""
    from mtcw_core.calibrate import derive_calibration
    from mtcw_core.calibration import CalibrationError
    from mtcw_core.ranging.ab import derive_reference
    from mtcw_core.results import Rejected

    if technique not in ("pb", "ab"):
        _fail(f"technique: calibration exists for pb and ab, not {technique!r}")
    rec = _open(recording)
    try:
        frames = tqdm(rec, total=len(rec), unit="frame", desc="calibrate", file=sys.stderr)
        cal = (derive_reference(frames, known_range, source=str(recording)) if technique == "ab" else
               derive_calibration(frames, known_range, source=str(recording)))
    except (CalibrationError, Rejected, RecordingError) as err:
        _fail(str(err))
    cal.save(output)
    typer.echo(json.dumps({"written": str(output), "tau0_s": cal.tau0_s, "tone_phases_rad": cal.tone_phases_rad,
                           "phase_std_rad": cal.phase_std_rad, "frames": cal.frames_used}, indent=2))


@app.command()
def bench(
    quick: bool = typer.Option(False, "--quick", help="a small grid for CI (2^16 samples, 3 frames)"),
    out: Path = typer.Option(Path("out/bench"), "-o", "--out", help="output folder (CSV, JSON, PNG, report.md)"),
    frames: Optional[int] = typer.Option(None, help="frames per cell"),
    samples: Optional[int] = typer.Option(None, help="override the scenes' record length"),
    scenes: Optional[str] = typer.Option(None, help="comma-separated scene names"),
    profiles: Optional[str] = typer.Option(None, help="comma-separated profiles"),
    losses: Optional[str] = typer.Option(None, help="comma-separated echo losses (dB)"),
    stream_json: Optional[Path] = typer.Option(None, help="include mtcw-bench-stream's stream.json in the report"),
    repeats: Optional[int] = typer.Option(None, min=1, help="timed repeats per cell, each with its interleaved "
                                          "references (default: the frame count; seed: its frames only)"),
    honesty: bool = typer.Option(False, "--honesty", help="the honesty map instead (issue 12; --quick, -o, --frames, "
                                                          "--profiles apply; more options: mtcw-bench-honesty --help)"),
    threads: int = typer.Option(1, min=0, help="BLAS/OpenMP threads of this process, as a worker's MTCW_THREADS "
                                               "(1: the chain on one core, like its one-core rfft reference; "
                                               "0: the libraries' own)"),
    fft_backend: str = typer.Option("pocketfft", help="FFT implementation of every transform, the rfft reference's "
                                    "too, as a worker's MTCW_FFT_BACKEND: pocketfft (scipy's) | pyfftw (FFTW; "
                                    "pip install 'mtcw\\[fftw]')"),
) -> None:
    """Measure the speed-accuracy trade: scenes x losses x profiles x methods, against the CRB,
    each cell timed against one rfft of its frame interleaved with the chain; stage breakdown and
    peak memory per profile."""
    import shlex

    if honesty:
        from mtcw_bench.honesty import main as honesty_main

        argv = (["--quick"] if quick else []) + ["-o", str(out)] + (["--frames", str(frames)] if frames else []) + (
            ["--profiles", profiles] if profiles else [])
        try:
            honesty_main(argv)
        except SystemExit as err:
            if err.code not in (None, 0):
                _fail(str(err.code))
        return

    from mtcw_bench.grid import GridSpec, cell_count, machine_info, run_grid, simulation_costs
    from mtcw_bench.report import write_report
    from mtcw_core.dsp.spectrum import use_fft_backend
    from services.worker import limit_threads

    limit_threads(threads)  # before machine_info, which records the pools' threads
    try:
        use_fft_backend(fft_backend)  # before machine_info, which records it
    except ValueError as err:
        _fail(str(err))

    def csv_list(v: Optional[str], default: list) -> list:
        return [x.strip() for x in v.split(",") if x.strip()] if v else default

    t_start = time.perf_counter()
    machine = machine_info()
    if quick:
        spec = GridSpec(scenes=csv_list(scenes, ["cw-bench", "six-tone"]),
                        losses_db=[float(x) for x in csv_list(losses, ["30", "55"])],
                        profiles=csv_list(profiles, ["fast", "balanced", "accurate", "seed"]), methods=["ml", "seed"],
                        frames=frames or 3, samples=samples or 2**16, seed_points=2**20, repeats=repeats)
    else:
        spec = GridSpec(scenes=csv_list(scenes, ["cw-bench", "six-tone", "moving-target", "low-coherence"]),
                        losses_db=[float(x) for x in csv_list(losses, ["20", "60", "80", "88", "94", "100"])],
                        profiles=csv_list(profiles, ["fast", "balanced", "accurate", "seed"]), methods=["ml", "seed"],
                        frames=frames or 16, samples=samples, repeats=repeats,
                        # the seed's resample-and-filter path costs ~1-3 s a frame: two losses, 4 frames
                        profile_losses={"seed": [20.0, 94.0]}, profile_frames={"seed": min(4, frames or 16)})
    for p in spec.profiles:
        _settings(p, None)
    n_cells = cell_count(spec)
    bar = tqdm(total=n_cells, unit="cell", desc="bench", file=sys.stderr)

    def progress(label: str) -> None:
        bar.set_postfix_str(label)
        bar.update(1)

    try:
        result = run_grid(spec, progress)
    except (SceneError, ValueError) as err:
        _fail(str(err))
    bar.close()
    result["simulation_costs"] = simulation_costs(spec.samples or 1_000_000, repeat=2 if quick else 3)
    machine["load_avg_end"] = machine_info()["load_avg"]
    result["machine"] = machine
    if stream_json is not None:
        try:
            result["stream"] = json.loads(stream_json.read_text())
        except (OSError, ValueError) as err:
            _fail(f"stream-json: {err}")
        if not isinstance(result["stream"], dict):
            _fail(f"stream-json: {stream_json} holds a {type(result['stream']).__name__}, not an object with `rows`")
    result["total_s"] = time.perf_counter() - t_start
    given = {"--quick": quick, "-o": out, "--frames": frames, "--samples": samples, "--scenes": scenes,
             "--profiles": profiles, "--losses": losses, "--repeats": repeats, "--stream-json": stream_json,
             "--fft-backend": fft_backend if fft_backend != "pocketfft" else None}
    cmd = "mtcw bench" + "".join(f" {k}" if v is True else f" {k} {shlex.quote(str(v))}"
                                 for k, v in given.items() if v not in (None, False))
    path = write_report(result, out, cmd)
    typer.echo(f"wrote {path} (and results.csv, results.json, PNG figures) for {len(result['cells'])} cells")


@app.command()
def snr(
    out: Path = typer.Option(Path("out/snr"), "-o", "--out", help="output folder (snr.csv, snr.json, snr.png)"),
    bandwidths: str = typer.Option("1e6,1e7,1e8", help="comma-separated electronic filter bandwidths (Hz)"),
    max_attenuation: float = typer.Option(120.0, help="largest echo attenuation (dB)"),
    step: float = typer.Option(1.0, help="attenuation step (dB)"),
    p_lo: float = typer.Option(5e-3, help="LO power (W)"),
    p_echo: float = typer.Option(10e-3, help="echo power before attenuation (W)"),
    gain_db: float = typer.Option(3.0, help="optical amplifier gain (dB); 0 = none"),
    n_sp: float = typer.Option(1.5, help="amplifier spontaneous-emission factor"),
    responsivity: float = typer.Option(0.7, help="detector responsivity (A/W)"),
    temperature: float = typer.Option(300.0, help="temperature (K)"),
    wavelength: float = typer.Option(1e-6, help="wavelength (m)"),
    filter_nm: float = typer.Option(2.0, help="optical filter full width (nm)"),
    solar_irradiance: float = typer.Option(0.75, help="solar spectral irradiance (W m^-2 nm^-1); 0 = night"),
    aperture_m2: Optional[float] = typer.Option(None, help="solar collection area (m^2); default one spatial "
                                                "mode of a white sunlit scene, lambda^2/pi"),
    receiver: str = typer.Option("balanced", help="balanced | single"),
) -> None:
    """SNR of one line against echo attenuation (the dissertation's Fig. 36): table, JSON and PNG."""
    from mtcw_bench.snr_figure import write_snr
    from mtcw_core.snr import Link

    try:
        bws = [float(b) for b in bandwidths.split(",") if b.strip()]
    except ValueError:
        _fail(f"bandwidths: {bandwidths!r} is not a comma-separated list of numbers")
    checks = {"bandwidths": min(bws, default=0.0) > 0, "max_attenuation": 0 <= max_attenuation <= 400,
              "step": 0 < step <= max(max_attenuation, 1.0), "p_lo": p_lo > 0, "p_echo": p_echo > 0,
              "gain_db": 0 <= gain_db <= 60, "n_sp": n_sp >= 1, "responsivity": responsivity > 0,
              "temperature": temperature > 0, "wavelength": wavelength > 0, "filter_nm": filter_nm > 0,
              "solar_irradiance": solar_irradiance >= 0, "aperture_m2": aperture_m2 is None or aperture_m2 > 0,
              "receiver": receiver in ("balanced", "single")}
    bad = [k for k, ok in checks.items() if not ok]
    if bad:
        _fail(f"{bad[0]}: out of range (see mtcw snr --help)")
    link = Link(wavelength_m=wavelength, p_lo_w=p_lo, p_echo_w=p_echo, temperature_k=temperature, gain_db=gain_db,
                n_sp=n_sp, responsivity_a_per_w=responsivity, solar_irradiance_w_per_m2_nm=solar_irradiance,
                aperture_area_m2=aperture_m2, filter_bandwidth_m=filter_nm * 1e-9, receiver=receiver)
    res = write_snr(link, out, bws, max_attenuation, step)
    att = res["attenuation_db"]
    every = max(1, round(10 / step))
    labels = list(res["curves"])
    typer.echo("attenuation_dB " + " ".join(f"{lb:>10s}" for lb in labels) + "  dominant noise")
    for k in range(0, len(att), every):
        typer.echo(f"{att[k]:14g} " + " ".join(f"{res['curves'][lb]['model_db'][k]:10.1f}" for lb in labels)
                   + f"  {res['curves'][labels[0]]['dominant'][k]}")
    def at(x):
        return "beyond the range" if x is None else f"{x:.1f} dB"

    for lb in labels:
        c = res["curves"][lb]
        typer.echo(f"{lb}: SNR 20 dB at {at(c['crossings_model']['20 dB'])}, 0 dB at {at(c['crossings_model']['0 dB'])} "
                   f"(Eq. 5.11 as printed: {at(c['crossings_eq_5_11']['20 dB'])}, {at(c['crossings_eq_5_11']['0 dB'])})")
    typer.echo(f"wrote {out / 'snr.csv'}, {out / 'snr.json'}, {out / 'snr.png'}")


@app.command("plan-tones")
def plan_tones_cmd(
    check: Optional[str] = typer.Option(None, "--check", help="evaluate these comma-separated tones (Hz) instead of planning"),
    unambiguous_range: float = typer.Option(15.0, "--range", help="required unambiguous range (m)"),
    resolution: float = typer.Option(1e-3, help="required range sigma at the design SNR (m)"),
    bandwidth: float = typer.Option(1e9, help="detector bandwidth (Hz)"),
    doppler: float = typer.Option(0.0, help="largest |Doppler| (Hz)"),
    grid: float = typer.Option(1e6, help="reference-clock grid of the synthesizers (Hz)"),
    tones: int = typer.Option(4, help="number of tones to plan"),
    snr_db: float = typer.Option(30.0, "--snr-db", help="design post-integration line SNR (dB)"),
    guard: float = typer.Option(1e6, help="extra clearance between lines (Hz)"),
    candidates: int = typer.Option(400, help="tone sets tried"),
    json_out: bool = typer.Option(False, "--json", help="print the report as JSON"),
) -> None:
    """Choose tones for a range, precision, band and Doppler -- or check a tone set (--check)."""
    from mtcw_core.planning import check_plan, plan_tones

    try:
        if check is not None:
            try:
                f = [float(x) for x in check.split(",") if x.strip()]
            except ValueError:
                _fail(f"check: {check!r} is not a comma-separated list of frequencies (Hz)")
            rep = check_plan(f, max_doppler_hz=doppler, detector_bandwidth_hz=bandwidth, design_snr_db=snr_db,
                             guard_hz=guard)
        else:
            rep = plan_tones(unambiguous_range_m=unambiguous_range, resolution_m=resolution,
                             detector_bandwidth_hz=bandwidth, max_doppler_hz=doppler, grid_hz=grid, n_tones=tones,
                             design_snr_db=snr_db, guard_hz=guard, candidates=candidates)
    except ValueError as err:
        _fail(str(err))
    if json_out:
        typer.echo(json.dumps({**rep.__dict__, "ok": rep.ok}, indent=2))
    else:
        for line in rep.notes:
            typer.echo(line)
    if check is not None and not rep.ok:
        raise typer.Exit(1)


#: a service still running this long (s) after its stop signal writes every thread's stack to
#: stderr (once; it goes on stopping): by design the acquisition node stops within ~10 s (its
#: end-of-run notice's poll and LINGER), a worker within its points' LINGER
STOP_STACKS_AFTER_S = 20.0


def _stop_on_signals():
    """A threading.Event set by SIGINT/SIGTERM (a service's clean stop).

    Once stopping, further SIGINT/SIGTERM are ignored: Ctrl-C reaches every process of the
    terminal's group and ``mtcw run`` then sends SIGTERM too, which would otherwise land during
    interpreter shutdown and end a clean stop as "killed by signal" (a stuck service is still
    SIGKILLed by the supervisor after its timeout). A stop still under way
    :data:`STOP_STACKS_AFTER_S` later writes the threads' stacks to stderr (faulthandler), whoever
    sent the signal: a hung stop shows where it hangs under any process manager.
    """
    import faulthandler
    import signal
    import threading

    stop = threading.Event()

    def handler(*_):
        stop.set()
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, signal.SIG_IGN)
        _stacks_to_stderr(faulthandler.dump_traceback_later, STOP_STACKS_AFTER_S, exit=False)

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handler)
    return stop


def _exit_zero_on_signals() -> None:
    """SIGINT/SIGTERM end the process with status 0 (for ``mtcw api``, a clean stop).

    uvicorn installs its own handlers while it serves, shuts down gracefully on the first
    signal, restores the handlers it found and then raises the signal again, "to trigger the
    expected behaviour": with the default handlers that ends the process killed by SIGTERM
    (status -15) after a clean stop. With this handler in place that re-raised signal exits 0,
    and a signal before uvicorn serves ends the process at once, also with 0.
    """
    import signal

    def handler(*_):
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, signal.SIG_IGN)
        raise SystemExit(0)

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handler)


LOG_FORMATS = ("text", "json")


def _logging(verbose: bool = False) -> None:
    """Log to stderr as text, or as one JSON object per line when ``MTCW_LOG_FORMAT=json``
    (keys ``time``, ``level``, ``logger``, ``message``, ``process`` and ``exc_info`` on errors,
    by python-json-logger)."""
    import logging
    import os

    fmt = os.environ.get("MTCW_LOG_FORMAT", "text").strip().lower()
    if fmt not in LOG_FORMATS:
        _fail(f"settings: MTCW_LOG_FORMAT: {fmt!r} is not one of {', '.join(LOG_FORMATS)}")
    handler = logging.StreamHandler(sys.stderr)
    if fmt == "json":
        from pythonjsonlogger.json import JsonFormatter

        handler.setFormatter(JsonFormatter("%(asctime)s %(levelname)s %(name)s %(message)s %(process)d",
                                           rename_fields={"asctime": "time", "levelname": "level", "name": "logger"}))
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s %(message)s"))
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, handlers=[handler], force=True)
    _stacks_on_sigusr1()


def _stacks_on_sigusr1() -> None:
    """SIGUSR1 writes every thread's Python stack to stderr and the service goes on (the standard
    library's faulthandler): a service that does not stop can be asked where it is before it is
    killed (the supervisor and the soak do so)."""
    import faulthandler
    import signal

    if hasattr(signal, "SIGUSR1"):
        _stacks_to_stderr(faulthandler.register, signal.SIGUSR1, all_threads=True)


def _stacks_to_stderr(call, *args, **kwargs) -> None:
    """A faulthandler ``call`` whose stacks go to stderr; skipped where stderr has no file
    descriptor (embedded use, Typer's CliRunner): a service never fails for want of its stacks."""
    try:
        call(*args, file=sys.stderr, **kwargs)
    except (AttributeError, OSError, RuntimeError, ValueError):
        pass


def _service_settings(cls, **flags):
    from services.settings import load

    try:
        return load(cls, **flags)
    except ValueError as err:
        _fail(f"settings: {err}")


@app.command()
def acquire(
    source: Optional[str] = typer.Option(None, help="sim | replay | scope | scope-sim | module:Class  [env MTCW_SOURCE; "
                                                    "default sim]"),
    scene: Optional[str] = typer.Option(None, help="scene for the simulator [MTCW_SCENE; default cw-bench]"),
    recording: Optional[Path] = typer.Option(None, help="SigMF recording to replay [MTCW_RECORDING]"),
    rate: Optional[float] = typer.Option(None, "--rate", help="frames/s, 0 = as fast as possible [MTCW_RATE_HZ]"),
    frames: Optional[int] = typer.Option(None, help="stop after N frames, 0 = never [MTCW_FRAMES]"),
    loop: Optional[bool] = typer.Option(None, "--loop/--no-loop", help="replay: loop [MTCW_LOOP; default loop]"),
    source_name: Optional[str] = typer.Option(None, help="source name in every frame [MTCW_SOURCE_NAME]"),
    seed: Optional[int] = typer.Option(None, help="simulator seed"),
    resource: Optional[str] = typer.Option(None, help="scope: VISA resource, e.g. TCPIP::192.168.1.20::INSTR "
                                                      "[MTCW_RESOURCE]"),
    visa_library: Optional[str] = typer.Option(None, help="scope: PyVISA backend, @py (default) | sim | a vendor "
                                                          "VISA library [MTCW_VISA_LIBRARY]"),
    tones_hz: Optional[str] = typer.Option(None, help="scope: the bench's tones, Hz, comma-separated "
                                                      "[MTCW_TONES_HZ]"),
    wavelength_m: Optional[float] = typer.Option(None, help="scope: the bench laser's wavelength [MTCW_WAVELENGTH_M]"),
    record_length: Optional[int] = typer.Option(None, help="scope: points per record [MTCW_RECORD_LENGTH]"),
    sample_rate: Optional[float] = typer.Option(None, help="scope: sample rate, S/s [MTCW_SAMPLE_RATE_HZ]"),
    data_width: Optional[int] = typer.Option(None, help="scope: 1 or 2 bytes per point [MTCW_DATA_WIDTH; "
                                                        "default 2]"),
) -> None:
    """Acquisition node: publish frames (PUSH to workers, PUB to monitors).

    Sources: sim, replay, scope (a Tektronix MDO3 over VISA: docs/scope.md), scope-sim (the same
    path against a simulated MDO3 of --scene), module:Class. Every scope setting is also an
    environment variable (MTCW_TRIGGER_SOURCE, MTCW_VERTICAL_SCALE_V, ...: docs/scope.md).
    """
    from services.acquisition import run_acquisition
    from services.auth import CurveKeyError
    from services.sources.scope import ScopeError
    from services.sockets import SocketError
    from services.settings import AcquisitionSettings

    _logging()
    st = _service_settings(AcquisitionSettings, source=source, scene=scene, recording=recording, rate_hz=rate,
                           frames=frames, loop=loop, source_name=source_name, seed=seed, resource=resource,
                           visa_library=visa_library, tones_hz=tones_hz, wavelength_m=wavelength_m,
                           record_length=record_length, sample_rate_hz=sample_rate, data_width=data_width)
    stop = _stop_on_signals()
    try:
        run_acquisition(st, stop)
    except (SocketError, CurveKeyError) as err:
        _fail(f"settings: {err}")
    except ScopeError as err:  # scope_max_failures reached
        _fail(f"scope: {err}", 1)
    except (SceneError, RecordingError, ValueError) as err:
        _fail(str(err))


scope_app = typer.Typer(no_args_is_help=True, help="The Tektronix MDO3 scope source: check the link, measure it.")
app.add_typer(scope_app, name="scope")


@scope_app.command("check")
def scope_check(
    resource: str = typer.Option(..., help="VISA resource (TCPIP::host::INSTR), or 'sim' for a simulated MDO3 of "
                                           "--scene"),
    visa_library: str = typer.Option("@py", help="@py | sim (pyvisa-sim, mtcw's MDO34 definition: resources "
                                                 "TCPIP::mdo34-sim::INSTR, TCPIP::mdo34-unlocked::INSTR) | a "
                                                 "vendor VISA library"),
    channel: str = typer.Option("CH1", help="channel to transfer"),
    record_length: Optional[int] = typer.Option(None, help="set this record length first"),
    sample_rate: Optional[float] = typer.Option(None, help="ask for this sample rate first (S/s)"),
    data_width: int = typer.Option(2, help="1 or 2 bytes per point"),
    external_reference: bool = typer.Option(True, "--external-reference/--internal-reference",
                                            help="require the external 10 MHz reference to be locked"),
    acquire: bool = typer.Option(True, "--acquire/--no-acquire", help="run one acquisition and transfer it"),
    scene: str = typer.Option("cw-bench", help="scene of the simulated MDO3 (--resource sim)"),
    timeout: float = typer.Option(5.0, help="VISA timeout, s"),
) -> None:
    """Check the link to a scope: identify, configure, reference lock, one acquisition. Prints JSON;
    exits 1 naming the cause when something fails."""
    from services.sources.scope import Mdo3, ScopeConfig, ScopeError

    _logging()
    server = None
    vertical = None
    if resource == "sim":
        from services.sources.scope_sim import ScopeSimServer, SimulatedMdo3, autoset

        try:
            sc = load_scene(scene)
        except SceneError as err:
            _fail(str(err))
        rl = record_length or 100_000
        fs = sample_rate or sc.digitizer.sample_rate_hz
        server = ScopeSimServer(SimulatedMdo3(sc, seed=1))
        resource, visa_library, record_length, sample_rate = server.resource, "@py", rl, fs
        vertical = tuple(autoset(sc, rl, fs, seed=1).values())[:1]
    report: dict = {"resource": resource, "visa_library": visa_library}
    scope = Mdo3(resource, visa_library, timeout)
    try:
        report["idn"] = scope.open()
        cfg = ScopeConfig(channels=(channel.upper(),), record_length=record_length, sample_rate_hz=sample_rate,
                          vertical=vertical, data_width=data_width, external_reference=external_reference)
        report["in_force"] = scope.configure(cfg)
        report["reference"] = scope.reference_state()
        if acquire:
            t0 = time.perf_counter()
            report["numacq"] = scope.acquire()
            wf = scope.read_waveform(channel.upper(), report["in_force"]["record_length"],
                                     report["in_force"]["sample_rate_hz"])
            v = wf.volts()
            report["waveform"] = {"points": int(wf.codes.size), "dtype": str(wf.codes.dtype),
                                  "sample_rate_hz": 1.0 / wf.xincr_s, "xzero_s": wf.xzero_s,
                                  "volts_min": float(v.min()), "volts_max": float(v.max()),
                                  "codes_min": int(wf.codes.min()), "codes_max": int(wf.codes.max()),
                                  "seconds": round(time.perf_counter() - t0, 4)}
        report["ok"] = True
    except ScopeError as err:
        report.update(ok=False, reason=err.reason, error=str(err))
    finally:
        scope.close()
        if server is not None:
            server.close()
    typer.echo(json.dumps(report, indent=2))
    if not report["ok"]:
        raise typer.Exit(1)


@scope_app.command("bench")
def scope_bench(
    resource: Optional[str] = typer.Option(None, help="a real scope's VISA resource; default: the simulated MDO3"),
    visa_library: str = typer.Option("@py", help="PyVISA backend"),
    record_length: int = typer.Option(1_000_000, help="points per record"),
    width: list[int] = typer.Option([1, 2], "--width", help="DATa:WIDth to measure (repeat)"),
    frames: int = typer.Option(20, min=1, help="acquisitions per width"),
) -> None:
    """Transfer rate of the scope path (MB/s of CURVe?, frames/s of whole acquisitions)."""
    from mtcw_bench.scope import bench_transfer
    from services.sources.scope import ScopeError

    if any(w not in (1, 2) for w in width):
        _fail(f"width: {width}: each must be 1 or 2")
    try:
        rows = bench_transfer(record_length, tuple(width), frames, resource, visa_library)
    except ScopeError as err:
        _fail(f"scope: {err}", 1)
    typer.echo(json.dumps({"command": "mtcw scope bench " + " ".join(
        [f"--record-length {record_length}", *[f"--width {w}" for w in width], f"--frames {frames}"]
        + ([f"--resource {resource}"] if resource else [])), "results": rows}, indent=2))


@app.command()
def worker(
    profile: Optional[str] = typer.Option(None, help="chain profile [MTCW_PROFILE; default balanced]"),
    calibration: Optional[Path] = typer.Option(None, help="calibration file [MTCW_CALIBRATION]"),
    name: Optional[str] = typer.Option(None, help="worker name in logs [MTCW_NAME]"),
    technique: Optional[str] = typer.Option(None, help="ranging technique pb | ab | pe | ptof [MTCW_TECHNIQUE; "
                                                       "default pb]"),
    timing_jitter_s: Optional[float] = typer.Option(None, "--timing-jitter-s", help="the digitizer's known rms "
                                                    "timing jitter (s) [MTCW_TIMING_JITTER_S; default 0]"),
    tone_phase_sigma_rad: Optional[float] = typer.Option(None, "--tone-phase-sigma-rad", help=TONE_PHASE_HELP +
                                                         " [MTCW_TONE_PHASE_SIGMA_RAD; default 0]"),
    laser_linewidth_hz: Optional[float] = typer.Option(None, "--laser-linewidth-hz", help="the bench's laser FWHM "
                                                       "(Hz) [MTCW_LASER_LINEWIDTH_HZ; default 0: coherent]"),
    lo_path_difference_m: Optional[float] = typer.Option(None, "--lo-path-difference-m", help="LO minus echo "
                                                         "internal path (m) [MTCW_LO_PATH_DIFFERENCE_M; default 0]"),
    accumulate: Optional[int] = typer.Option(None, "--accumulate", help="static targets beyond the laser's "
                                             "coherence: whole-band IF mixing averaged over the last K frames of "
                                             "each source (1-32) [MTCW_ACCUMULATE; default 0: off]"),
    sideband_direction: Optional[bool] = typer.Option(None, "--sideband-direction/--no-sideband-direction",
                                                      help="one photodiode: say the direction of motion where the "
                                                      "sidebands' own Doppler shift decides its sign "
                                                      "[MTCW_SIDEBAND_DIRECTION; default off: unknown]"),
    track: Optional[int] = typer.Option(None, "--track", help=TRACK_HELP + " [MTCW_TRACK; default 0: off]"),
    track_max_speed: Optional[float] = typer.Option(None, "--track-max-speed", help=TRACK_SPEED_HELP +
                                                    " [MTCW_TRACK_MAX_SPEED_MPS]"),
    fft_backend: Optional[str] = typer.Option(None, "--fft-backend", help="FFT implementation: pocketfft | pyfftw "
                                              "(pip install 'mtcw\\[fftw]') [MTCW_FFT_BACKEND; default pocketfft]"),
) -> None:
    """Worker: frames in, the chain (PB-MTCW by default), points out."""
    from mtcw_core.calibration import CalibrationError
    from services.settings import WorkerSettings
    from services.worker import Worker

    _logging()
    st = _service_settings(WorkerSettings, profile=profile, calibration=calibration, name=name, technique=technique,
                           timing_jitter_s=timing_jitter_s, tone_phase_sigma_rad=tone_phase_sigma_rad,
                           laser_linewidth_hz=laser_linewidth_hz,
                           lo_path_difference_m=lo_path_difference_m, accumulate=accumulate,
                           sideband_direction=sideband_direction, fft_backend=fft_backend, track=track,
                           track_max_speed_mps=track_max_speed)
    try:
        w = Worker(st)
    except CalibrationError as err:
        _fail(str(err))
    except ValueError as err:  # SocketError, CurveKeyError: they name the settings field
        _fail(f"settings: {err}")
    w.run(_stop_on_signals())


@app.command()
def api(
    host: Optional[str] = typer.Option(None, help="HTTP bind address [MTCW_HOST; default 127.0.0.1]"),
    port: Optional[int] = typer.Option(None, help="HTTP port [MTCW_PORT; default 8000]"),
) -> None:
    """API: latest points, history, health and Prometheus metrics over HTTP."""
    _exit_zero_on_signals()
    from services.api import serve
    from services.settings import ApiSettings

    _logging()
    serve(_service_settings(ApiSettings, host=host, port=port))


@app.command()
def keys(
    directory: Path = typer.Argument(..., help="where to keep the keys (give it as MTCW_CURVE_DIR)"),
    client: Optional[list[str]] = typer.Option(None, "--client", help="client identities to make and allow in "
                                                                     "(repeat; default: worker, recorder)"),
) -> None:
    """Make CurveZMQ keys: the servers' pair, one pair per client, and the allow-list (idempotent)."""
    from services.auth import AUTHORIZED_DIR, DEFAULT_CLIENTS, make_keys

    try:
        written = make_keys(directory, tuple(client) if client else DEFAULT_CLIENTS)
    except (OSError, ValueError) as err:
        _fail(f"keys: {err}")
    allowed = sorted(p.stem for p in (directory / AUTHORIZED_DIR).glob("*.key"))
    typer.echo(json.dumps({"curve_dir": str(directory), "made": sorted(written), "authorized": allowed}))


@app.command()
def record(
    output: Path = typer.Option(..., "-o", "--output", help="recording prefix"),
    frames: int = typer.Option(10, "-n", "--frames", help="frames to record (0 = until Ctrl-C)"),
) -> None:
    """Subscribe to the monitor stream and write the frames to a SigMF recording."""
    from services.monitor import record as do_record
    from services.settings import TransportSettings

    _logging()
    st = _service_settings(TransportSettings)
    stop = _stop_on_signals()
    bar = tqdm(total=frames or None, unit="frame", desc="record", file=sys.stderr)
    try:
        sub = do_record(st, output, frames, stop, progress=lambda n: bar.update(1))
    except RecordingError as err:
        _fail(str(err))
    except ValueError as err:  # SocketError, CurveKeyError: they name the settings field
        _fail(f"settings: {err}")
    bar.close()
    typer.echo(json.dumps({"written": str(output), "frames": sub.gaps.received - sub.refused,
                           "dropped": sub.gaps.dropped, "malformed": sub.malformed, "refused": sub.refused}))


@app.command()
def run(
    scene: str = typer.Option("cw-bench", help="scene file or bundled scene name"),
    profile: str = typer.Option("balanced", help="chain profile of the workers"),
    technique: str = typer.Option("pb", help="ranging technique of the workers: pb | ab | pe | ptof"),
    calibration: Optional[Path] = typer.Option(None, help="calibration file for the workers (ab needs one)"),
    workers: int = typer.Option(1, min=1, max=64, help="number of worker processes"),
    rate: float = typer.Option(5.0, help="frames/s from the simulator (0 = as fast as it goes)"),
    port: int = typer.Option(8000, min=0, max=65535, help="HTTP port of the API (127.0.0.1; 0 = a free one)"),
    base_port: int = typer.Option(5555, min=0, max=65533, help="first of three ZeroMQ ports (frames, monitor, "
                                                               "points); 0 = free ports, as the services report them"),
    track: int = typer.Option(0, "--track", help=TRACK_HELP + "; each worker tracks its share of the frames"),
) -> None:
    """All-in-one: simulator + worker(s) + API on loopback. Ctrl-C or SIGTERM stops everything."""
    from services.settings import WorkerSettings
    from services.supervisor import Supervisor, free_ports

    try:
        sc = load_scene(scene)
    except SceneError as err:
        _fail(str(err))
    _service_settings(WorkerSettings, profile=profile, technique=technique, track=track)  # bad ones fail here
    # with --base-port 0 the services bind free ports and report them, except the monitor port: the
    # API (started first) subscribes to it for the live view's spectra, so it is chosen here
    ports = (base_port, base_port + 1, base_port + 2) if base_port else (0, free_ports(1)[0], 0)
    env = {f"MTCW_{k}_ENDPOINT": f"tcp://127.0.0.1:{p}" for k, p in zip(("FRAMES", "MONITOR", "POINTS"), ports)}
    sup = Supervisor(env=env)
    # the binding ends first, each reporting its endpoints; the workers connect to them
    sup.add("api", "api", "--host", "127.0.0.1", "--port", str(port), reports=True)
    sup.add("acquisition", "acquire", "--source", "sim", "--scene", scene, "--rate", str(rate), reports=True,
            env={"MTCW_WAIT_FOR_WORKERS": str(workers), "MTCW_WAIT_FOR_WORKER_S": "60"})
    for i in range(workers):
        sup.add(f"worker-{i}", "worker", "--profile", profile, "--technique", technique, "--name", f"worker-{i}",
                *(("--calibration", str(calibration.resolve())) if calibration is not None else ()),
                *(("--track", str(track)) if track else ()))

    def banner(s: Supervisor) -> None:
        url = s.endpoints["http_url"]
        typer.echo(f"mtcw run: scene {sc.name} ({sc.description}); {workers} worker(s), profile {profile}\n"
                   f"  live view    : {url}/\n"
                   f"  latest point : curl {url}/v1/points/latest\n"
                   f"  history      : curl '{url}/v1/points?limit=10'\n"
                   f"  health       : curl {url}/readyz\n"
                   f"  metrics      : curl {url}/metrics\n"
                   f"  API docs     : {url}/docs\n"
                   f"  raw frames   : mtcw record -o out/capture -n 10   "
                   f"(with MTCW_MONITOR_ENDPOINT={s.endpoints['monitor_endpoint']})\n"
                   f"Ctrl-C or SIGTERM stops everything.")

    codes = sup.run_until_signal(on_start=banner)
    why = codes.pop("_why")
    typer.echo(f"mtcw run: stopped ({why}); exit codes {codes}")
    if why and ("exited" in str(why) or "failed" in str(why)):
        raise typer.Exit(1)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
