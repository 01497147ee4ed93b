"""Service settings: flags override environment (``MTCW_...``), which overrides the defaults.

Every setting is validated (pydantic); an error names the field. Each service logs its
settings at start-up, and each socket the options in force on it, read back from ZeroMQ
(:mod:`services.sockets`), so that endpoints, high-water marks, LINGER and the drop policy of a
running daemon are never a guess.
"""

from __future__ import annotations

import logging
from pathlib import Path
import math
from typing import Annotated, Literal, Optional

from pydantic import Field, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from mtcw_core.dsp.validate import WAVELENGTH_RANGE_M

from .auth import AUTHORIZED_DIR, SERVER, is_local_endpoint
from .ordering import DEFAULT_MAX_JUMP
from .sockets import (DEFAULT_FRAME_HWM, DEFAULT_FRAME_LINGER_MS, DEFAULT_MAX_FRAME_BYTES, DEFAULT_MAX_POINT_BYTES,
                      DEFAULT_POINT_HWM, DEFAULT_POINT_LINGER_MS, DEFAULT_POINT_SEND_TIMEOUT_MS)

log = logging.getLogger("mtcw")

#: the longest wait a setting may ask for (s): a day; longer ones overflow ZeroMQ's poll timeouts
MAX_WAIT_S = 86_400.0
#: the highest frame rate a setting may ask for (frames/s)
MAX_RATE_HZ = 1e6


def _path_given(v):
    """An empty path (``MTCW_ENDPOINTS_FILE=""``) would be the current directory: refused."""
    if isinstance(v, str) and not v.strip():
        raise ValueError("an empty path")
    return v


class TransportSettings(BaseSettings):
    """ZeroMQ endpoints and queue policy shared by the services.

    The stable ends bind: the acquisition node binds ``frames_endpoint`` (PUSH, to workers) and
    ``monitor_endpoint`` (PUB, to recorders and monitors); the API binds ``points_endpoint``
    (PULL). Workers and recorders connect, and reconnect by themselves. The defaults of the
    socket options are named, with their reasons, in :mod:`services.sockets`.
    """

    model_config = SettingsConfigDict(env_prefix="MTCW_", extra="forbid", validate_default=True, allow_inf_nan=False)

    frames_endpoint: str = Field("tcp://127.0.0.1:5555", description="acquisition PUSH -> workers (bind: port 0 "
                                                                      "takes a free one)")
    monitor_endpoint: str = Field("tcp://127.0.0.1:5556", description="acquisition PUB -> recorders")
    points_endpoint: str = Field("tcp://127.0.0.1:5557", description="workers -> API PULL")
    hwm: int = Field(DEFAULT_FRAME_HWM, ge=1, le=100_000,
                     description="high-water mark (messages) of the frame sockets (PUSH, PUB, PULL, SUB)")
    linger_ms: int = Field(DEFAULT_FRAME_LINGER_MS, ge=-1, description="LINGER of the acquisition node's frame "
                                                                       "sockets (ms; -1 = wait for ever)")
    drop_policy: Literal["drop", "block"] = Field(
        "drop", description="when no worker can take a frame: drop it (counted) or wait for one")
    points_hwm: int = Field(DEFAULT_POINT_HWM, ge=1, le=10_000_000,
                            description="high-water mark (messages) of the point sockets (worker PUSH, API PULL)")
    points_linger_ms: int = Field(DEFAULT_POINT_LINGER_MS, ge=-1, description="LINGER of the worker's point socket")
    points_send_timeout_ms: int = Field(DEFAULT_POINT_SEND_TIMEOUT_MS, ge=0, description="a worker waits this long "
                                        "for the API to take a point, then counts it undelivered")
    max_frame_bytes: int = Field(DEFAULT_MAX_FRAME_BYTES, ge=1, description="MAXMSGSIZE of frame receivers (bytes "
                                 "per message part; a peer sending more is disconnected)")
    max_point_bytes: int = Field(DEFAULT_MAX_POINT_BYTES, ge=1, description="MAXMSGSIZE of the API's point receiver")
    metrics_host: str = Field("127.0.0.1", description="bind address of the Prometheus exporters")
    endpoints_file: Optional[Path] = Field(None, description="once bound, write the bound endpoints here as JSON "
                                                             "(for a parent that started this service on port 0)")
    curve_dir: Optional[Path] = Field(None, description="CurveZMQ keys made by `mtcw keys DIR`: every socket "
                                      "encrypted, peers checked against DIR/authorized; required when an endpoint "
                                      "is not on this machine")
    curve_client: str = Field("worker", min_length=1, pattern=r"^[A-Za-z0-9_.-]+$",
                              description="this service's client identity in curve_dir/clients (connecting sockets)")

    @field_validator("frames_endpoint", "monitor_endpoint", "points_endpoint")
    @classmethod
    def _endpoint(cls, v: str) -> str:
        if "://" not in v:
            raise ValueError(f"{v!r} is not a ZeroMQ endpoint (tcp://host:port, ipc://path)")
        return v

    _paths = field_validator("endpoints_file", "curve_dir", mode="before")(_path_given)

    @field_validator("curve_dir")
    @classmethod
    def _keys(cls, v: Optional[Path]) -> Optional[Path]:
        try:
            found = v is None or ((v / f"{SERVER}.key").is_file() and (v / AUTHORIZED_DIR).is_dir())
        except (OSError, ValueError) as err:  # a name too long for the file system, a NUL
            raise ValueError(f"cannot be a directory name ({getattr(err, 'strerror', None) or err})") from None
        if not found:
            raise ValueError(f"{v} holds no CurveZMQ keys ({SERVER}.key, {AUTHORIZED_DIR}/): make them with "
                             f"`mtcw keys {v}`")
        return v

    @model_validator(mode="after")
    def _local_unless_authenticated(self) -> "TransportSettings":
        if self.curve_dir is None:
            for name in ("frames_endpoint", "monitor_endpoint", "points_endpoint"):
                ep = getattr(self, name)
                if not is_local_endpoint(ep):
                    raise ValueError(f"{name}: {ep} is reachable from other machines; set curve_dir (keys from "
                                     f"`mtcw keys DIR`) to authenticate and encrypt, or bind to 127.0.0.1")
        return self


#: record lengths a Tektronix MDO3 offers (points)
SCOPE_RECORD_LENGTHS = (1_000, 10_000, 100_000, 1_000_000, 5_000_000, 10_000_000)
#: most tones a frame may carry (the chain's validate stage refuses more)
MAX_TONES = 16


def _comma_list(v):
    """``"5e8,7e8"`` (a flag or ``MTCW_...``) or a JSON list as a list; None and lists as they are."""
    if isinstance(v, str):
        text = v.strip()
        if text.startswith("["):
            import json

            try:
                return json.loads(text)
            except ValueError:
                raise ValueError(f"{v!r} is neither a JSON list nor comma-separated values") from None
        return [p.strip() for p in text.split(",") if p.strip()]
    return v


class AcquisitionSettings(TransportSettings):
    source: str = Field("sim", description="sim | replay | scope | scope-sim | module:Class (a FrameSource plug-in)")
    scene: str = Field("cw-bench", description="scene file or bundled scene name (source sim)")
    recording: Optional[Path] = Field(None, description="SigMF recording (source replay)")
    rate_hz: float = Field(0.0, ge=0, le=MAX_RATE_HZ, description="frames per second; 0 = as fast as the source goes")
    loop: bool = Field(True, description="replay: start again at the end")
    frames: int = Field(0, ge=0, description="stop after this many frames (0 = run until stopped)")
    source_name: str = Field("bench", min_length=1, max_length=150, description="the `source` field of every frame")
    seed: Optional[int] = None
    metrics_port: int = Field(0, ge=0, le=65535, description="Prometheus exporter port (0 = off)")
    wait_for_worker_s: float = Field(5.0, ge=0, le=MAX_WAIT_S, description="before the first frame, wait this long for the "
                                                            "workers (wait_for_workers of them)")
    wait_for_workers: int = Field(1, ge=1, le=1024, description="how many workers to wait for before the first frame")
    end_timeout_s: float = Field(5.0, ge=0, le=MAX_WAIT_S, description="at the end of a run, wait this long to hand the "
                                                        "end-of-run notice (and queued frames) to a worker")
    state_file: Optional[Path] = Field(None, description="the run's frame count, kept current before every send "
                                       "(a memory-mapped file): a node restarted after a kill sends the killed "
                                       "run's end-of-run notice, so its lost tail is counted")

    # -- the scope (source scope, scope-sim): docs/scope.md --------------------------------------------------
    resource: Optional[str] = Field(None, min_length=1, max_length=256,
                                    description="VISA resource of the scope (TCPIP::host::INSTR, "
                                                "TCPIP::host::4000::SOCKET, USB::...)")
    visa_library: str = Field("@py", min_length=1, description="PyVISA backend: @py (pyvisa-py), sim (pyvisa-sim "
                              "with mtcw's MDO34 definition), FILE.yaml@sim, or a vendor VISA library's path")
    tones_hz: Annotated[Optional[list[float]], NoDecode] = Field(
        None, description="the bench's modulation tones (Hz, comma-separated); the scope does not know them "
                          "(scope-sim: the scene's)")
    wavelength_m: Optional[float] = Field(None, ge=WAVELENGTH_RANGE_M[0], le=WAVELENGTH_RANGE_M[1],
                                          description="the bench laser's wavelength (m, within what the chain "
                                          "accepts; scope-sim: the scene's)")
    receiver: Optional[Literal["single", "balanced", "iq"]] = Field(
        None, description="the bench's receiver (scope: single unless given; scope-sim: the scene's)")
    scope_channels: Annotated[Optional[list[str]], NoDecode] = Field(
        None, description="scope channels carrying the detector: CH1 (single/balanced) or CH1,CH2 (I,Q)")
    scope_pulse_ref_channel: Optional[str] = Field(None, pattern=r"^CH[1-4]$",
                                                   description="channel carrying the quasi-CW reference pulse")
    pulse_period_s: Optional[float] = Field(None, gt=0, le=1, description="quasi-CW gate period (s)")
    pulse_duty: Optional[float] = Field(None, gt=0, le=1, description="quasi-CW gate duty cycle")
    pulse_delay_s: float = Field(0.0, ge=0, le=1, description="quasi-CW gate delay (s)")
    record_length: Optional[int] = Field(None, description=f"points per record, one of "
                                         f"{', '.join(map(str, SCOPE_RECORD_LENGTHS))} (unset: the scope's)")
    sample_rate_hz: Optional[float] = Field(None, gt=0, le=1e11, description="sample rate asked of the scope "
                                            "(S/s; unset: the scope's); it must report this rate")
    sample_rate_rel_tol: float = Field(1e-6, gt=0, le=0.1, description="largest relative difference between the "
                                       "rate asked and the rate the scope reports")
    vertical_scale_v: Optional[float] = Field(None, ge=1e-3, le=10, description="V/div of the scope channels "
                                              "(unset: the scope's; scope-sim: fitted to the scene)")
    vertical_offset_v: float = Field(0.0, ge=-100, le=100, description="offset (V) of the scope channels")
    termination: Optional[Literal["FIFTY", "MEG"]] = Field(None, description="input termination (unset: the "
                                                                            "scope's)")
    trigger_source: Optional[str] = Field(None, pattern=r"^(AUX|CH[1-4])$", description="trigger source: AUX "
                                          "(Aux In, the bench's trigger) or CH1..CH4 (unset: the scope's)")
    trigger_level_v: Optional[float] = Field(None, ge=-100, le=100, description="trigger level (V)")
    external_reference: bool = Field(True, description="lock the time base to the 10 MHz at REF IN; no frame is "
                                     "acquired while ROSc:STATE? is not LOCKED")
    data_width: Literal[1, 2] = Field(2, description="bytes per point of the transfer (DATa:WIDth)")
    data_encoding: Literal["SRIBINARY", "RIBINARY"] = Field("SRIBINARY", description="DATa:ENCdg: signed LSB "
                                                            "first (no swap) or MSB first")
    acquire_mode: Literal["SAMPLE", "HIRES"] = Field("SAMPLE", description="ACQuire:MODe")
    visa_timeout_s: float = Field(5.0, gt=0, le=3600, description="VISA timeout of every read (a trigger is "
                                  "waited for this long)")
    visa_chunk_bytes: int = Field(1 << 20, ge=1024, le=1 << 30, description="largest single VISA read of a block")
    retry_backoff_s: float = Field(0.5, ge=0, le=MAX_WAIT_S, description="first wait after a scope failure; "
                                   "doubled after each further one")
    retry_backoff_max_s: float = Field(30.0, ge=0, le=MAX_WAIT_S, description="longest wait between retries")
    scope_max_failures: int = Field(0, ge=0, description="give up after this many scope failures in a row "
                                    "(0 = retry for ever)")
    scope_sim_pool: int = Field(0, ge=0, le=1000, description="scope-sim: simulate this many acquisitions and "
                                "repeat them (0 = every one anew)")

    _acq_paths = field_validator("recording", "state_file", mode="before")(_path_given)
    _lists = field_validator("tones_hz", "scope_channels", mode="before")(_comma_list)

    @field_validator("tones_hz")
    @classmethod
    def _tones(cls, v: Optional[list[float]]) -> Optional[list[float]]:
        if v is None:
            return v
        if not 1 <= len(v) <= MAX_TONES:
            raise ValueError(f"{len(v)} tones; give 1 to {MAX_TONES}")
        if any(not math.isfinite(f) or f <= 0 or f > 1e12 for f in v):
            raise ValueError(f"{v}: every tone must be a finite frequency in (0, 1e12] Hz")
        if len(set(v)) != len(v):
            raise ValueError(f"{v}: a tone is given twice")
        return v

    @field_validator("scope_channels")
    @classmethod
    def _channels(cls, v: Optional[list[str]]) -> Optional[list[str]]:
        if v is None:
            return v
        v = [c.strip().upper() for c in v]
        if not v or any(c not in ("CH1", "CH2", "CH3", "CH4") for c in v) or len(set(v)) != len(v):
            raise ValueError(f"{v}: give distinct channels among CH1, CH2, CH3, CH4")
        return v

    @field_validator("record_length")
    @classmethod
    def _record_length(cls, v: Optional[int]) -> Optional[int]:
        if v is not None and v not in SCOPE_RECORD_LENGTHS:
            raise ValueError(f"{v} is not a record length of the scope ({', '.join(map(str, SCOPE_RECORD_LENGTHS))})")
        return v

    @model_validator(mode="after")
    def _scope_complete(self) -> "AcquisitionSettings":
        if self.source not in ("scope", "scope-sim"):
            return self
        if self.source == "scope":
            for name, why in (("resource", "the scope's VISA resource (TCPIP::host::INSTR)"),
                              ("tones_hz", "the bench's tone plan (the scope does not know it)"),
                              ("wavelength_m", "the bench laser's wavelength")):
                if getattr(self, name) is None:
                    raise ValueError(f"{name}: source scope needs {why}")
        receiver = self.receiver or "single"
        if self.scope_channels is not None and len(self.scope_channels) != (2 if receiver == "iq" else 1):
            raise ValueError(f"scope_channels: {self.scope_channels} for receiver {receiver!r}; give "
                             f"{'two (I, Q)' if receiver == 'iq' else 'one'}")
        if self.scope_pulse_ref_channel and self.scope_pulse_ref_channel in (self.scope_channels or []):
            raise ValueError(f"scope_pulse_ref_channel: {self.scope_pulse_ref_channel} is a detector channel too")
        if (self.pulse_period_s is None) != (self.pulse_duty is None):
            raise ValueError("pulse_duty: give pulse_period_s and pulse_duty together (quasi-CW gate)")
        if self.retry_backoff_max_s < self.retry_backoff_s:
            raise ValueError(f"retry_backoff_max_s: {self.retry_backoff_max_s} is less than retry_backoff_s "
                             f"({self.retry_backoff_s})")
        return self

    @field_validator("recording")
    @classmethod
    def _exists(cls, v: Optional[Path]) -> Optional[Path]:
        if v is None:
            return v
        try:
            found = v.exists() or v.with_suffix(".sigmf-meta").exists() or Path(str(v) + ".sigmf-meta").exists()
        except (OSError, ValueError) as err:  # a name too long for the file system, a NUL
            raise ValueError(f"cannot be a file name ({getattr(err, 'strerror', None) or err})") from None
        if not found:
            raise ValueError(f"{v} does not exist")
        return v


class WorkerSettings(TransportSettings):
    profile: str = Field("balanced", description="chain profile: fast | balanced | accurate | seed")
    technique: Literal["pb", "ab", "pe", "ptof"] = Field("pb", description="ranging technique (ChainSettings.technique)")
    timing_jitter_s: float = Field(0.0, ge=0, le=1e-6, description="the digitizer's known rms timing jitter (s); "
                                                                   "enters every range sigma")
    tone_phase_sigma_rad: float = Field(0.0, ge=0, le=math.pi, description="the RF synthesizers' known rms phase "
                                        "drift per tone since calibration (rad); enters every range sigma")
    laser_linewidth_hz: float = Field(0.0, ge=0, le=1e12, description="the bench's laser (Lorentzian FWHM, Hz): "
                                      "where it is incoherent at the echo's delay a speed is unknown, not 0, and "
                                      "the square stage ranges from the squared record; 0: coherent everywhere")
    lo_path_difference_m: float = Field(0.0, ge=-1e4, le=1e4, description="optical path of the LO minus the echo's "
                                        "internal path (m)")
    sideband_direction: bool = Field(False, description="one photodiode: say the direction of motion where the "
                                     "sidebands' own Doppler shift decides its sign (ChainSettings.sideband_direction;"
                                     " off: direction unknown)")
    calibration: Optional[Path] = Field(None, description="calibration file from `mtcw calibrate`")
    accumulate: int = Field(0, ge=0, le=32, description="static targets beyond the laser's coherence: range from "
                            "the whole band's digital IF mixing averaged over the last K frames of each source "
                            "(1-32; 0: off, the chain per frame); docs/reach.md")
    track: int = Field(0, ge=0, le=64, description="range rate over frames: each target's ranges over its last K "
                       "frames of the worker's share of a source (3-64; 0: off): a speed where the laser is "
                       "incoherent, the direction on one photodiode (range_rate_mps; mtcw_core.ranging.track)")
    track_max_speed_mps: Optional[float] = Field(None, gt=0, description="with track: the fastest range rate a "
                                                 "target may have (m/s; default: each point's own bound, its "
                                                 "Doppler speed or the search's largest: a laser incoherent at "
                                                 "the target needs it)")
    name: str = Field("worker", description="worker name in logs")
    metrics_port: int = Field(0, ge=0, le=65535, description="Prometheus exporter port (0 = off)")
    threads: int = Field(1, ge=0, le=1024, description="threads of the numerical libraries (OpenBLAS/OpenMP) in "
                         "this worker; 1: a worker takes one core and more cores are used by more workers (the "
                         "libraries' own threads spin and doubled the CPU per frame for no gain in speed); "
                         "0: the libraries' default")
    fft_backend: str = Field("pocketfft", description="FFT implementation of this worker's transforms: pocketfft "
                             "(scipy's own) | pyfftw (FFTW through pyFFTW, `pip install 'mtcw[fftw]'`: the "
                             "1e6-sample spectrum's real transform ~4x faster; FFTW is GPL)")

    _worker_paths = field_validator("calibration", mode="before")(_path_given)

    @field_validator("track")
    @classmethod
    def _track(cls, v: int) -> int:
        if 0 < v < 3:
            raise ValueError(f"{v}: a rate needs a window of at least 3 frames (0: off)")
        return v

    @field_validator("fft_backend")
    @classmethod
    def _fft_backend(cls, v: str) -> str:
        from mtcw_core.dsp.spectrum import fft_backend_module

        fft_backend_module(v)  # an unknown name, or pyfftw not installed: a ValueError naming fft_backend
        return v

    @field_validator("profile")
    @classmethod
    def _profile(cls, v: str) -> str:
        from mtcw_core.chain import PROFILES

        if v not in PROFILES:
            raise ValueError(f"unknown profile {v!r} (one of {', '.join(PROFILES)})")
        return v


class ApiSettings(TransportSettings):
    host: str = Field("127.0.0.1", description="HTTP bind address (loopback unless told otherwise)")
    port: int = Field(8000, ge=0, le=65535)
    store_path: str = Field("out/mtcw-api.sqlite3", min_length=1,
                            description="SQLite file of the history, latest points, counters and reorder state "
                                        "(parents created; one API per file); ':memory:' keeps nothing across "
                                        "restarts")
    retention_points: int = Field(100_000, ge=1, le=100_000_000, description="points kept for /v1/points (the "
                                  "oldest are deleted, in batches)")
    history: Optional[int] = Field(None, ge=1, le=100_000_000, description="the old name of retention_points "
                                   "(MTCW_HISTORY); retention_points wins when both are set")
    retention_s: float = Field(0.0, ge=0, description="also delete points served longer ago than this "
                                                      "(s; 0 = no age limit)")
    reorder_timeout_s: float = Field(2.0, gt=0, le=MAX_WAIT_S, description="wait this long for a missing seq before "
                                                            "counting it dropped")
    reorder_max: int = Field(256, ge=1, description="points held for reordering before gaps are declared")
    max_seq_jump: int = Field(DEFAULT_MAX_JUMP, ge=1, description="the largest seq gap one message may declare "
                              "(frames; at least reorder_max): a point further ahead, or an end-of-run notice "
                              "further beyond what was seen, is refused until a second point confirms the jump")
    max_future_s: float = Field(60.0, gt=0, description="refuse points and notices triggered more than this "
                                                        "ahead of the API's clock (s)")
    stale_after_s: float = Field(5.0, gt=0, le=MAX_WAIT_S, description="/readyz fails when the last frame is older")
    view_rate_hz: float = Field(1.0, ge=0, le=50, description="live view (/): spectra and cost curves explained "
                                "per second at most, from the monitor stream, while a page is open (0 = none)")
    view_profile: Literal["fast", "balanced", "accurate", "seed"] = Field(
        "balanced", description="chain profile of the live view's explanations")

    @field_validator("store_path")
    @classmethod
    def _store_path(cls, v: str) -> str:
        try:
            is_dir = v != ":memory:" and Path(v).expanduser().is_dir()
        except (OSError, ValueError) as err:  # a name too long for the file system, a NUL
            raise ValueError(f"cannot be a file name ({getattr(err, 'strerror', None) or err})") from None
        except RuntimeError:  # "~name" of no such user (pathlib cannot find that home directory)
            raise ValueError(f"{v!r}: no home directory to expand {v.split('/')[0]!r} to") from None
        if is_dir:
            raise ValueError(f"{v} is a directory; give a file in it (e.g. {Path(v) / 'mtcw-api.sqlite3'})")
        return v

    @model_validator(mode="after")
    def _jump_covers_reordering(self) -> "ApiSettings":
        if self.history is not None and "retention_points" not in self.model_fields_set:
            self.retention_points = self.history
        if self.max_seq_jump < self.reorder_max:
            # name the field the user gave (reorder_max alone, past the default jump: that one)
            if "reorder_max" in self.model_fields_set and "max_seq_jump" not in self.model_fields_set:
                raise ValueError(f"reorder_max: {self.reorder_max} is more than max_seq_jump ({self.max_seq_jump}): "
                                 f"points held for reordering would be refused; raise max_seq_jump too")
            raise ValueError(f"max_seq_jump: {self.max_seq_jump} is less than reorder_max ({self.reorder_max}): "
                             f"points held for reordering would be refused")
        return self


def load(cls: type[BaseSettings], **flags) -> BaseSettings:
    """Settings from flags (None = not given), environment and defaults; raises ValueError naming fields."""
    try:
        return cls(**{k: v for k, v in flags.items() if v is not None})
    except ValidationError as err:
        msgs = []
        for e in err.errors():
            msg = e["msg"].removeprefix("Value error, ")
            loc = ".".join(str(p) for p in e["loc"])
            msgs.append(f"{loc}: {msg}" if loc else msg)  # a check across fields names its field itself
        raise ValueError("; ".join(msgs)) from None


def log_settings(service: str, settings: BaseSettings) -> None:
    log.info("%s settings: %s", service, settings.model_dump_json())
