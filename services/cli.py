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


def main() -> None:
    app()


if __name__ == "__main__":
    main()
