"""A Tektronix MDO3 oscilloscope as a frame source, over VISA (PyVISA; ``pyvisa-py`` by default).

:class:`Mdo3` is the connection: open a resource (``TCPIP::host::INSTR`` (VXI-11),
``TCPIP::host::4000::SOCKET``, ``USB::...``), identify (``*IDN?``), configure what the
settings name (leaving the rest as the scope has it), and, per frame, check that the external
10 MHz reference is locked, run one single-sequence acquisition, read ``ACQuire:NUMACq?`` and
transfer each channel: ``WFMOutpre`` scaling, then ``CURVe?`` as an IEEE 488.2 definite-length
block read in chunks, its byte count checked against the header and the header against
``NR_Pt`` x ``DATa:WIDth`` (partial transfers are a known failure of VISA stacks: they are an
error here, never a short frame). Every failure is a :class:`ScopeError` whose ``reason`` is one
of :data:`REASONS`.

:class:`ScopeSource` turns that into :class:`~mtcw_core.frame.Frame` objects for the acquisition
node: the samples are the scope's codes with ``volts = code*scale + offset`` (``scale`` = YMUlt,
``offset`` = YZEro - YOFf*YMUlt; float32 volts when channels differ in scaling), ``fs_hz`` is
1/XINcr of the record, and the tone plan, wavelength, receiver and gate timing are the bench's,
from settings. A failure is logged with its cause, counted (``on_error(reason)``, the node's
``mtcw_acquisition_errors_total{reason}``), the connection is closed, and the source waits with
exponential back-off before it connects, configures and acquires again; the node's publisher
(seq, run, ledger) is untouched and no frame of a failed acquisition is yielded.

Why PyVISA and not Tektronix's ``tm_devices``: ``tm_devices`` (3.x) knows the MDO3's command
tree but has no waveform transfer for that family (``curve_query`` is implemented for the
2-series and the 4/5/6-series ``TekScope`` only), it reaches instruments through its own device
manager and configuration files, and it brings a dozen further dependencies (zeroconf, USB,
GPIB, serial, requests). The MDO3's commands used here are few and documented in its
programmer manual; PyVISA with ``pyvisa-py`` needs no vendor VISA.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Callable, Iterator, Optional

import numpy as np

from mtcw_core.frame import Frame, PulseInfo

log = logging.getLogger("mtcw.scope")

#: the ``reason`` label of ``mtcw_acquisition_errors_total`` for each failure
REASONS = (
    "timeout",              # the instrument did not answer within visa_timeout_s
    "connection",           # could not open the resource, or the connection was lost
    "transfer_incomplete",  # a block stopped before its header's byte count (instrument gone mid-transfer)
    "garbled_block",        # CURVe? did not answer a definite-length block #<n><length>
    "block_size",           # the block's byte count is not NR_Pt x DATa:WIDth
    "record_length",        # NR_Pt (or the record length read back) is not the record length asked
    "sample_rate",          # the scope samples at another rate than asked (read back, or 1/XINcr)
    "reference_unlocked",   # the external 10 MHz reference is not locked: the scope refuses to run
    "instrument_error",     # the scope refused a command (*ESR? / ALLEv?)
    "bad_answer",           # an answer that is not what the command returns (a number, a state)
)

#: maximum bytes asked of VISA in one read of a block (records above this are read in chunks)
DEFAULT_CHUNK_BYTES = 1 << 20


def sim_definition() -> str:
    """The path of the pyvisa-sim definition of an MDO34's control plane shipped with mtcw
    (``mdo3.yaml``: ``TCPIP::mdo34-sim::INSTR`` locked, ``TCPIP::mdo34-unlocked::INSTR`` not)."""
    from importlib import resources

    return str(resources.files("services.sources") / "mdo3.yaml")


def visa_backend(visa_library: str) -> str:
    """PyVISA's backend string for the ``visa_library`` setting (``sim``: the shipped definition)."""
    return f"{sim_definition()}@sim" if visa_library == "sim" else visa_library


class ScopeError(Exception):
    """A scope failure with its cause: ``reason`` (one of :data:`REASONS`) and a message."""

    def __init__(self, reason: str, message: str) -> None:
        assert reason in REASONS, reason
        super().__init__(f"{reason}: {message}")
        self.reason = reason


@dataclass(frozen=True)
class ScopeConfig:
    """What to set on the scope (``None``: leave the scope's own setting) and what to expect.

    Attributes
    ----------
    channels : tuple of str
        Scope channels in frame order (``("CH1",)``, ``("CH1", "CH2")`` for I/Q, then the
        reference pulse's channel).
    record_length : int or None
        Points per record.
    sample_rate_hz : float or None
        Asked through the horizontal scale: ``HORizontal:SCAle = record_length / (10 fs)``.
    vertical : tuple of (scale V/div, offset V) or None
        One pair per channel, or None to keep the scope's.
    termination : str or None
        ``FIFTY`` or ``MEG``.
    trigger_source : str or None
        ``AUX`` (the rear/front Aux In), ``CH1`` ...
    trigger_level_v : float or None
    external_reference : bool
        Lock the time base to the 10 MHz at REF IN and refuse to acquire while it is unlocked.
    data_width : int
        1 or 2 bytes per point.
    encoding : str
        ``SRIBINARY`` (signed, LSB first: no byte swap here) or ``RIBINARY`` (signed, MSB first).
    acquire_mode : str
        ``SAMPLE`` or ``HIRES``.
    sample_rate_rel_tol : float
        Largest relative difference between the rate asked and the rate the scope reports.
    """

    channels: tuple[str, ...] = ("CH1",)
    record_length: Optional[int] = None
    sample_rate_hz: Optional[float] = None
    vertical: Optional[tuple[tuple[float, float], ...]] = None
    termination: Optional[str] = None
    trigger_source: Optional[str] = None
    trigger_level_v: Optional[float] = None
    external_reference: bool = True
    data_width: int = 2
    encoding: str = "SRIBINARY"
    acquire_mode: str = "SAMPLE"
    sample_rate_rel_tol: float = 1e-6


@dataclass(frozen=True)
class Waveform:
    """One channel's record as transferred.

    Attributes
    ----------
    codes : ndarray, shape (n,)
        int8 (width 1) or little-endian int16 (width 2).
    ymult_v, yoff, yzero_v : float
        ``volts = (code - yoff) * ymult_v + yzero_v``.
    xincr_s, xzero_s : float
        Sample interval and the time of the first point relative to the trigger.
    """

    codes: np.ndarray
    ymult_v: float
    yoff: float
    yzero_v: float
    xincr_s: float
    xzero_s: float

    @property
    def scale(self) -> float:
        return self.ymult_v

    @property
    def offset(self) -> float:
        return self.yzero_v - self.yoff * self.ymult_v

    def volts(self) -> np.ndarray:
        """Volts, float64, shape (n,)."""
        return (self.codes.astype(np.float64) - self.yoff) * self.ymult_v + self.yzero_v


def _visa_error(err: Exception, during: str) -> ScopeError:
    """A PyVISA/OS error as a ScopeError with its reason."""
    import pyvisa

    if isinstance(err, pyvisa.errors.VisaIOError):
        if err.error_code == pyvisa.constants.StatusCode.error_timeout:
            return ScopeError("timeout", f"no answer to {during} within the VISA timeout ({err.abbreviation})")
        return ScopeError("connection", f"{during}: {err.abbreviation}: {err.description}")
    return ScopeError("connection", f"{during}: {type(err).__name__}: {err}")


def _no_delay(inst) -> None:
    """TCP_NODELAY on a pyvisa-py raw socket session (best effort): commands go out at once
    instead of waiting for the scope's delayed ACK of the previous one (Nagle)."""
    import socket

    try:
        sock = inst.visalib.sessions[inst.session].interface
        if isinstance(sock, socket.socket):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    except Exception:  # noqa: BLE001 -- another backend or session kind: nothing to do
        pass


class Mdo3:
    """A connection to an MDO3 (or an instrument answering its commands).

    Parameters
    ----------
    resource : str
        VISA resource string.
    visa_library : str
        PyVISA backend: ``@py`` (pyvisa-py, default), ``sim`` (pyvisa-sim with the shipped
        :func:`sim_definition`), ``path.yaml@sim``, or the path of a vendor VISA library.
    timeout_s : float
        VISA timeout for every read (an acquisition waits for its trigger this long too).
    chunk_bytes : int
        Largest single VISA read of a block.
    """

    def __init__(self, resource: str, visa_library: str = "@py", timeout_s: float = 5.0,
                 chunk_bytes: int = DEFAULT_CHUNK_BYTES) -> None:
        self.resource_name = resource
        self.visa_library = visa_library
        self.timeout_s = timeout_s
        self.chunk_bytes = chunk_bytes
        self._rm = None
        self._inst = None
        self.idn = ""

    # -- the link -------------------------------------------------------------------------
    def open(self) -> str:
        """Open the resource and identify it; returns the ``*IDN?`` answer."""
        import pyvisa

        try:
            self._rm = pyvisa.ResourceManager(visa_backend(self.visa_library))
        except (OSError, ValueError, pyvisa.errors.Error) as err:
            raise ScopeError("connection", f"visa_library {self.visa_library!r}: {err}") from None
        try:
            self._inst = self._rm.open_resource(self.resource_name, read_termination="\n", write_termination="\n",
                                                timeout=int(self.timeout_s * 1000))
        except (OSError, ValueError, pyvisa.errors.Error) as err:
            self.close()
            raise ScopeError("connection", f"cannot open {self.resource_name}: {err}") from None
        _no_delay(self._inst)
        self.idn = self.query("*IDN?")
        if "TEKTRONIX" not in self.idn.upper() or "MDO3" not in self.idn.upper():
            log.warning("scope: %s identifies as %r, not a Tektronix MDO3; going on with the MDO3's commands",
                        self.resource_name, self.idn)
        return self.idn

    def close(self) -> None:
        for obj in (self._inst, self._rm):
            if obj is not None:
                try:
                    obj.close()
                except Exception:  # noqa: BLE001 -- closing a broken session must not raise
                    pass
        self._inst = self._rm = None

    @property
    def is_open(self) -> bool:
        return self._inst is not None

    def write(self, cmd: str) -> None:
        try:
            self._inst.write(cmd)
        except Exception as err:  # noqa: BLE001 -- pyvisa, socket and backend errors alike
            raise _visa_error(err, cmd) from None

    def query(self, cmd: str) -> str:
        try:
            return self._inst.query(cmd).strip()
        except Exception as err:  # noqa: BLE001
            raise _visa_error(err, cmd) from None

    def query_float(self, cmd: str) -> float:
        ans = self.query(cmd)
        try:
            v = float(ans.split()[-1])
        except (ValueError, IndexError):
            raise ScopeError("bad_answer", f"{cmd} answered {ans[:80]!r}, not a number") from None
        if not math.isfinite(v):
            raise ScopeError("bad_answer", f"{cmd} answered {ans[:80]!r}")
        return v

    def check_errors(self, what: str) -> None:
        """Raise ``instrument_error`` naming the scope's events when ``*ESR?`` shows an error."""
        esr = int(self.query_float("*ESR?"))
        if esr & 0b0011_0100:  # command, execution and query errors
            events = self.query("ALLEV?")
            raise ScopeError("instrument_error", f"the scope refused a command while {what} (*ESR? {esr}): {events}")

    # -- configuration --------------------------------------------------------------------
    def configure(self, cfg: ScopeConfig) -> dict:
        """Set what ``cfg`` names, check for errors, read back and check what is in force.

        Returns
        -------
        dict
            The settings in force, as the scope reports them (logged by the caller).
        """
        self.write("HEADER OFF")
        self.write("*CLS")
        self.write("ROSC:SOURCE EXTERNAL" if cfg.external_reference else "ROSC:SOURCE INTERNAL")
        self.write(f"ACQUIRE:MODE {cfg.acquire_mode}")
        self.write("ACQUIRE:STOPAFTER SEQUENCE")
        if cfg.record_length is not None:
            self.write(f"HORIZONTAL:RECORDLENGTH {cfg.record_length:d}")
        if cfg.sample_rate_hz is not None:
            rl = cfg.record_length or int(self.query_float("HORIZONTAL:RECORDLENGTH?"))
            self.write(f"HORIZONTAL:SCALE {rl / (10.0 * cfg.sample_rate_hz):.6E}")
        for i, ch in enumerate(cfg.channels):
            self.write(f"SELECT:{ch} ON")
            if cfg.vertical is not None:
                scale, offset = cfg.vertical[i]
                self.write(f"{ch}:SCALE {scale:.6E}")
                self.write(f"{ch}:OFFSET {offset:.6E}")
            if cfg.termination is not None:
                self.write(f"{ch}:TERMINATION {cfg.termination}")
        if cfg.trigger_source is not None:
            self.write(f"TRIGGER:A:EDGE:SOURCE {cfg.trigger_source}")
        if cfg.trigger_level_v is not None:
            src = cfg.trigger_source or self.query("TRIGGER:A:EDGE:SOURCE?").split()[-1].upper()
            self.write(f"TRIGGER:A:LEVEL:{'AUXIN' if src.startswith('AUX') else src} {cfg.trigger_level_v:.6E}")
        self.write(f"DATA:ENCDG {cfg.encoding}")
        self.write(f"DATA:WIDTH {cfg.data_width:d}")
        self.write("DATA:START 1")
        rl = int(self.query_float("HORIZONTAL:RECORDLENGTH?"))
        self.write(f"DATA:STOP {rl:d}")
        self.check_errors("configuring")
        fs = self.query_float("HORIZONTAL:SAMPLERATE?")
        in_force = {"idn": self.idn, "record_length": rl, "sample_rate_hz": fs,
                    "reference": self.query("ROSC:SOURCE?"), "trigger_source": self.query("TRIGGER:A:EDGE:SOURCE?"),
                    "data_width": int(self.query_float("DATA:WIDTH?")), "encoding": self.query("DATA:ENCDG?"),
                    "channels": {ch: {"scale_v_per_div": self.query_float(f"{ch}:SCALE?"),
                                      "offset_v": self.query_float(f"{ch}:OFFSET?")} for ch in cfg.channels}}
        if cfg.record_length is not None and rl != cfg.record_length:
            raise ScopeError("record_length", f"asked for {cfg.record_length} points, the scope has {rl}")
        if cfg.sample_rate_hz is not None and abs(fs / cfg.sample_rate_hz - 1) > cfg.sample_rate_rel_tol:
            raise ScopeError("sample_rate", f"asked for {cfg.sample_rate_hz:.6g} S/s, the scope samples at "
                                            f"{fs:.6g} S/s (HORizontal:SAMPLERate?); set a rate the scope offers "
                                            f"at {rl} points")
        if cfg.external_reference:
            self.check_reference()
        return in_force

    def reference_state(self) -> str:
        return self.query("ROSC:STATE?").split()[-1].upper()

    def check_reference(self) -> None:
        """Refuse (``reference_unlocked``) unless the external 10 MHz reference is locked."""
        state = self.reference_state()
        if state != "LOCKED":
            raise ScopeError("reference_unlocked", f"the scope's time base is not locked to the external 10 MHz "
                                                   f"reference (ROSc:STATE? {state}): refusing to acquire; check "
                                                   f"the 10 MHz cable at REF IN and ROSc:SOUrce EXTernal")

    # -- acquisition ---------------------------------------------------------------------
    def acquire(self) -> int:
        """One single-sequence acquisition, waited for with ``*OPC?``; returns ``ACQuire:NUMACq?``."""
        # one message: a write followed by another write would wait for the first one's delayed ACK
        if self.query("ACQUIRE:STATE ON;*OPC?").split()[-1] != "1":
            raise ScopeError("bad_answer", "*OPC? did not answer 1 after ACQuire:STATE ON")
        return int(self.query_float("ACQUIRE:NUMACQ?"))

    def read_waveform(self, channel: str, expect_points: Optional[int] = None,
                      expect_fs_hz: Optional[float] = None, rel_tol: float = 1e-6) -> Waveform:
        """Transfer one channel of the last acquisition.

        Raises
        ------
        ScopeError
            ``record_length`` (NR_Pt is not ``expect_points``), ``sample_rate`` (1/XINcr is not
            ``expect_fs_hz``), ``garbled_block``, ``block_size``, ``transfer_incomplete``,
            ``timeout``, ``connection``, ``bad_answer``.
        """
        ans = self.query(f"DATA:SOURCE {channel};:WFMOUTPRE:NR_PT?;YMULT?;YOFF?;YZERO?;XINCR?;XZERO?;BYT_NR?;BYT_OR?")
        fields = [f.split()[-1] if f.split() else "" for f in ans.split(";")]
        try:
            nr_pt = int(float(fields[0]))
            ymult, yoff, yzero, xincr, xzero = (float(f) for f in fields[1:6])
            width = int(float(fields[6]))
            order = fields[7].upper()
        except (ValueError, IndexError):
            raise ScopeError("bad_answer", f"WFMOutpre of {channel} answered {ans[:120]!r}") from None
        if not all(math.isfinite(v) for v in (ymult, yoff, yzero, xincr, xzero)) or ymult <= 0 or xincr <= 0:
            raise ScopeError("bad_answer", f"WFMOutpre of {channel}: implausible scaling {ans[:120]!r}")
        if width not in (1, 2) or order not in ("LSB", "MSB"):
            raise ScopeError("bad_answer", f"WFMOutpre of {channel}: BYT_Nr {width}, BYT_Or {order}")
        if expect_points is not None and nr_pt != expect_points:
            raise ScopeError("record_length", f"{channel} holds {nr_pt} points (WFMOutpre:NR_Pt?), "
                                              f"{expect_points} asked")
        if expect_fs_hz is not None and abs(1.0 / (xincr * expect_fs_hz) - 1) > rel_tol:
            raise ScopeError("sample_rate", f"{channel} was sampled at {1 / xincr:.6g} S/s (1/WFMOutpre:XINcr?), "
                                            f"{expect_fs_hz:.6g} S/s asked")
        raw = self._read_block(channel, nr_pt * width)
        dtype = np.dtype("i1") if width == 1 else np.dtype("<i2" if order == "LSB" else ">i2")
        codes = np.frombuffer(raw, dtype=dtype)
        if dtype.byteorder == ">":
            codes = codes.astype("<i2")
        return Waveform(codes, ymult, yoff, yzero, xincr, xzero)

    def _read_block(self, channel: str, expect_bytes: int) -> bytearray:
        """``CURVe?``'s definite-length block, read in chunks, every count checked."""
        self.write("CURVE?")
        inst = self._inst
        got, n = 0, None
        # binary data holds 0x0A bytes: no read may stop at the termination character
        term, inst.read_termination = inst.read_termination, None
        try:
            head = inst.read_bytes(2)
            if head[:1] != b"#" or not head[1:2].isdigit() or head[1:2] == b"0":
                raise ScopeError("garbled_block", f"CURVe? of {channel} began {bytes(head)!r}, not a definite-length "
                                                  f"block header #<n><length>")
            digits = inst.read_bytes(int(head[1:2]))
            if not digits.isdigit():
                raise ScopeError("garbled_block", f"CURVe? of {channel}: block length {bytes(digits)!r} is not a "
                                                  f"number")
            n = int(digits)
            if n != expect_bytes:
                raise ScopeError("block_size", f"CURVe? of {channel} announced {n} bytes, NR_Pt x BYT_Nr is "
                                               f"{expect_bytes}")
            buf = bytearray(n)
            view = memoryview(buf)
            while got < n:
                chunk = inst.read_bytes(min(self.chunk_bytes, n - got))
                view[got:got + len(chunk)] = chunk
                got += len(chunk)
            end = inst.read_bytes(1)
            if end != b"\n":
                raise ScopeError("garbled_block", f"CURVe? of {channel}: {bytes(end)!r} after the block, not its "
                                                  f"terminator")
            return buf
        except ScopeError:
            raise
        except Exception as err:  # noqa: BLE001 -- pyvisa, socket and backend errors alike
            if n is not None:  # the header came: the block stopped part-way
                raise ScopeError("transfer_incomplete", f"CURVe? of {channel} stopped part-way: {got} of "
                                                        f"{expect_bytes} bytes came in whole chunks ({type(err).__name__}: {err})") from None
            raise _visa_error(err, f"CURVe? of {channel}") from None
        finally:
            try:
                inst.read_termination = term
            except Exception:  # noqa: BLE001 -- a session already broken; it is closed next
                pass


class ScopeSource:
    """Frames from an MDO3, one single-sequence acquisition each; faults retried with back-off.

    Parameters
    ----------
    settings : AcquisitionSettings
        ``resource``, ``visa_library``, the scope fields, and the bench's tone plan.
    stop : threading.Event, optional
        Ends the back-off waits (a clean stop of the node).
    on_error : callable, optional
        Called with the reason of each failure (the node's error counter).
    on_missed : callable, optional
        Called with the number of acquisitions the scope made that the node did not read
        (``ACQuire:NUMACq?`` above 1 after a single sequence).
    config : ScopeConfig, optional
        Overrides the one built from ``settings`` (``scope-sim`` gives its autoset vertical).
    """

    def __init__(self, settings, stop: Optional[threading.Event] = None,
                 on_error: Optional[Callable[[str], None]] = None,
                 on_missed: Optional[Callable[[int], None]] = None,
                 config: Optional[ScopeConfig] = None, resource: Optional[str] = None) -> None:
        settings = settings.model_copy(update=defaults(settings))
        self.settings = settings
        self.stop = stop or threading.Event()
        self.on_error = on_error
        self.on_missed = on_missed
        self.config = config or scope_config(settings)
        self.resource = resource or settings.resource
        self.scope: Optional[Mdo3] = None
        self.errors: dict[str, int] = {}
        self.missed = 0
        self.in_force: Optional[dict] = None
        self.wavelength_m = settings.wavelength_m
        self.tones_hz = tuple(settings.tones_hz)
        self.pulse = (PulseInfo(settings.pulse_period_s, settings.pulse_duty, settings.pulse_delay_s)
                      if settings.pulse_period_s is not None else None)
        self.names = (("i", "q") if settings.receiver == "iq" else ("pd",)) + (
            ("pulse_ref",) if settings.scope_pulse_ref_channel else ())

    def connect(self) -> dict:
        """Open, identify and configure; returns the settings in force (also logged)."""
        self.disconnect()
        scope = Mdo3(self.resource, self.settings.visa_library, self.settings.visa_timeout_s,
                     self.settings.visa_chunk_bytes)
        try:
            idn = scope.open()
            log.info("scope: %s is %s", self.resource, idn)
            self.in_force = scope.configure(self.config)
        except ScopeError:
            scope.close()
            raise
        self.scope = scope
        log.info("scope: settings in force: %s", self.in_force)
        return self.in_force

    def disconnect(self) -> None:
        """Close the VISA session (a later frame connects again)."""
        if self.scope is not None:
            self.scope.close()
            self.scope = None

    def close(self) -> None:
        """Release everything the source holds (the node calls this when it stops)."""
        self.disconnect()

    def read_frame(self) -> Frame:
        """One acquisition of every channel as a frame (connecting first if need be)."""
        if self.scope is None:
            self.connect()
        scope, cfg = self.scope, self.config
        if cfg.external_reference:
            scope.check_reference()
        numacq = scope.acquire()
        if numacq > 1:
            self.missed += numacq - 1
            if self.on_missed:
                self.on_missed(numacq - 1)
        rl = self.in_force["record_length"]
        fs = self.in_force["sample_rate_hz"]
        waves = [scope.read_waveform(ch, rl, fs, cfg.sample_rate_rel_tol) for ch in cfg.channels]
        same = all((w.ymult_v, w.yoff, w.yzero_v) == (waves[0].ymult_v, waves[0].yoff, waves[0].yzero_v)
                   for w in waves)
        if same:
            samples = np.stack([w.codes for w in waves])
            scale, offset = waves[0].scale, waves[0].offset
        else:  # one scale per frame on the wire: channels scaled differently travel as volts
            samples = np.stack([w.volts().astype(np.float32) for w in waves])
            scale, offset = 1.0, 0.0
        st = self.settings
        return Frame(samples=samples, fs_hz=1.0 / waves[0].xincr_s, tones_hz=self.tones_hz,
                     wavelength_m=self.wavelength_m, receiver=st.receiver, channels=self.names, scale=scale,
                     offset=offset, pulse=self.pulse, source=st.source_name,
                     t_ns=time.time_ns())

    def _failed(self, err: ScopeError) -> None:
        self.errors[err.reason] = self.errors.get(err.reason, 0) + 1
        if self.on_error:
            self.on_error(err.reason)
        self.disconnect()  # a session in an unknown state (half a block unread) is never reused

    def frames(self) -> Iterator[Frame]:
        """Frames until ``stop`` is set; failures are counted and retried after a back-off
        (``retry_backoff_s``, doubling up to ``retry_backoff_max_s``). After
        ``scope_max_failures`` failures in a row (0 = never) the last one is raised."""
        st = self.settings
        failures = 0
        try:
            while not self.stop.is_set():
                try:
                    frame = self.read_frame()
                except ScopeError as err:
                    self._failed(err)
                    failures += 1
                    if st.scope_max_failures and failures >= st.scope_max_failures:
                        log.error("scope: %s; giving up after %d failures in a row", err, failures)
                        raise
                    delay = min(st.retry_backoff_max_s, st.retry_backoff_s * 2 ** (failures - 1))
                    log.error("scope: %s; frame not published; retrying in %.2f s (failure %d in a row)",
                              err, delay, failures)
                    if self.stop.wait(delay):
                        return
                    continue
                if failures:
                    log.info("scope: acquiring again after %d failure(s)", failures)
                failures = 0
                yield frame
        finally:
            self.disconnect()


def defaults(settings) -> dict:
    """The scope settings left unset that have a default: receiver ``single``, the detector on
    CH1 (CH1, CH2 for I/Q)."""
    receiver = settings.receiver or "single"
    return {"receiver": receiver,
            "scope_channels": settings.scope_channels or (["CH1", "CH2"] if receiver == "iq" else ["CH1"])}


def scope_config(settings) -> ScopeConfig:
    """The :class:`ScopeConfig` that :class:`AcquisitionSettings` ask for."""
    chans = tuple(settings.scope_channels) + (
        (settings.scope_pulse_ref_channel,) if settings.scope_pulse_ref_channel else ())
    vertical = None
    if settings.vertical_scale_v is not None:
        vertical = tuple((settings.vertical_scale_v, settings.vertical_offset_v) for _ in chans)
    return ScopeConfig(channels=chans, record_length=settings.record_length, sample_rate_hz=settings.sample_rate_hz,
                       vertical=vertical, termination=settings.termination, trigger_source=settings.trigger_source,
                       trigger_level_v=settings.trigger_level_v, external_reference=settings.external_reference,
                       data_width=settings.data_width, encoding=settings.data_encoding,
                       acquire_mode=settings.acquire_mode, sample_rate_rel_tol=settings.sample_rate_rel_tol)
