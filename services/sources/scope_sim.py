"""A simulated Tektronix MDO3 behind a real VISA interface: SCPI over a TCP socket.

The waveform path of :mod:`services.sources.scope` is tested against this instrument, not a
mock of the driver: the driver talks to it through PyVISA and the pure-Python ``pyvisa-py``
backend (resource ``TCPIP::127.0.0.1::<port>::SOCKET``, as a real scope's socket server on port
4000), so commands, IEEE 488.2 blocks, chunked reads and timeouts go through the same code as
on a bench. Its waveforms are the physics simulator's (:class:`mtcw_core.simulate.Simulator`)
frames of a scene, sampled at the rate and record length the driver set, digitized by an 8-bit
ADC (``ACQuire:MODe SAMple``; 16 bits in ``HIRes``) with the channel's vertical scale, offset and
position, and sent as codes with the ``WFMOutpre`` scaling a real MDO3 reports::

    volts = (code - YOFf) * YMUlt + YZEro,   YMUlt = scale / 25 (DATa:WIDth 1) or scale / 6400 (2)

(25 codes per division in one byte, 256 times that in two; ``YOFf`` = position x codes per
division; ``YZEro`` = the channel's offset). ``CURVe?`` answers a definite-length block built by
:func:`pyvisa.util.to_ieee_block`.

**Faults** (:meth:`SimulatedMdo3.inject`), each for the next ``count`` occasions:

=================  ======================================================================
``timeout``        ``CURVe?`` is never answered (the VISA read times out)
``gone``           ``CURVe?`` sends its header and half the data, then the instrument
                   disconnects and refuses connections for ``down_s`` seconds
``truncated``      ``CURVe?`` sends its header and part of the data, then nothing
``garbled``        ``CURVe?`` answers a block whose header is not ``#<digit><length>``
``short_block``    ``CURVe?`` answers a well-formed block holding fewer points than NR_Pt
``record_length``  the acquisition holds half the record length set (NR_Pt says so too)
``sample_rate``    the acquisition runs at half the sample rate set (its XINcr says so),
                   as when someone turns the horizontal knob during a run
``unlocked``       ``ROSc:STATE?`` answers ``UNLOCKED`` (the external 10 MHz is lost)
``missed``         the sequence counts 3 acquisitions (``ACQuire:NUMACq?``): 2 the node never read
=================  ======================================================================

:class:`ScopeSimServer` serves one :class:`SimulatedMdo3` on a port of 127.0.0.1 (0 = a free one)
in a thread; ``mtcw acquire --source scope-sim`` and the tests start it.
"""

from __future__ import annotations

import collections
import logging
import math
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
from pyvisa.util import to_ieee_block

from mtcw_core.scene import Scene, load_scene, scene_variant
from mtcw_core.simulate import Simulator

from .scope import ScopeSource, scope_config

log = logging.getLogger("mtcw.scope_sim")

IDN = "TEKTRONIX,MDO34,SIM0001,CF:91.1CT FV:v1.30 (mtcw simulated instrument)"
#: record lengths an MDO3 offers (points)
RECORD_LENGTHS = (1_000, 10_000, 100_000, 1_000_000, 5_000_000, 10_000_000)
#: the MDO3's highest sample rate (S/s, 1 GHz models)
MAX_SAMPLE_RATE_HZ = 5e9
#: codes per vertical division in one byte; two bytes carry 256 times as many
CODES_PER_DIV = 25.0
FAULTS = ("timeout", "gone", "truncated", "garbled", "short_block", "record_length", "sample_rate", "unlocked",
          "missed")

# SCPI mnemonics: the upper-case part is the short form; either form, or anything between, is taken
_MNEMONICS = [
    "HORizontal", "RECOrdlength", "SCAle", "SAMPLERate", "ROSc", "SOUrce", "STATE", "OFFSet", "POSition",
    "COUPling", "TERmination", "SELect", "TRIGger", "A", "EDGE", "LEVel", "AUXin", "SLOpe", "ACQuire", "MODe",
    "STOPAfter", "NUMACq", "DATa", "ENCdg", "WIDth", "STARt", "STOP", "WFMOutpre", "NR_Pt", "YMUlt", "YOFf",
    "YZEro", "XINcr", "XZEro", "BYT_Nr", "BN_Fmt", "BYT_Or", "CURVe", "HEADer", "VERBose", "ALLEv", "EVENT",
    "EXTernal", "INTERnal", "SEQuence", "RUNSTop", "SAMple", "HIRes", "RIBinary", "SRIbinary", "FIFty", "MEG",
    "AUX", "RISe", "FALL", "ON", "OFF", "RUN", "DC", "AC", "LSB", "MSB", "RI", "RP",
]

_LONG = {m.upper() for m in _MNEMONICS}


def _canon(token: str) -> str:
    """The long upper-case form of one SCPI mnemonic (``hor`` -> ``HORIZONTAL``, ``CH2`` -> ``CH2``)."""
    t = token.strip().upper()
    if len(t) == 3 and t.startswith("CH") and t[2] in "1234":
        return t
    if t in _LONG:
        return t
    for m in _MNEMONICS:
        short = "".join(c for c in m if c.isupper() or c == "_" or c.isdigit())
        if t.startswith(short) and m.upper().startswith(t):
            return m.upper()
    return t


def _float(arg: str) -> float:
    v = float(arg)
    if not math.isfinite(v):
        raise ValueError(arg)
    return v


@dataclass
class _Channel:
    scale_v: float = 0.1
    offset_v: float = 0.0
    position_div: float = 0.0
    coupling: str = "DC"
    termination: str = "FIFTY"
    on: bool = False


@dataclass
class _Acquisition:
    volts: dict[str, np.ndarray]  # channel -> float64 volts, shape (n,)
    fs_hz: float
    record_length: int


@dataclass
class SimulatedMdo3:
    """The instrument: SCPI state, acquisitions from a scene, faults. No sockets (see :class:`ScopeSimServer`).

    Parameters
    ----------
    scene : Scene
        The bench: its digitizer's rate and record length are replaced by the scope's settings.
        Channel 1 carries the photodiode (or I), channel 2 Q (IQ receivers), the next one the
        quasi-CW reference pulse when the scene has one.
    seed : int, optional
        The simulator's seed.
    pool : int
        0: every acquisition is simulated anew. N > 0: the first N acquisitions of a setting are
        kept and repeated in turn (for measuring the transfer path, not the physics).
    """

    scene: Scene
    seed: Optional[int] = None
    pool: int = 0
    record_length: int = 10_000
    horizontal_scale_s: float = 1e-7
    reference: str = "INTERNAL"
    locked_external: bool = True
    channels: dict[str, _Channel] = field(default_factory=lambda: {f"CH{i}": _Channel(on=i == 1) for i in range(1, 5)})
    trigger_source: str = "CH1"
    trigger_level_v: dict[str, float] = field(default_factory=dict)
    acquire_mode: str = "SAMPLE"
    stop_after: str = "RUNSTOP"
    numacq: int = 0
    data_source: str = "CH1"
    data_encoding: str = "RIBINARY"
    data_width: int = 1
    data_start: int = 1
    data_stop: int = 10_000_000
    header: bool = True
    esr: int = 0
    events: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.faults: collections.Counter[str] = collections.Counter()
        self._acq: Optional[_Acquisition] = None
        self._sims: dict[tuple, Simulator] = {}
        self._pools: dict[tuple, list[_Acquisition]] = {}
        self._pool_next = 0
        self._blocks: dict[tuple, bytes] = {}  # pooled acquisitions: their blocks, built once
        self.lock = threading.Lock()
        self.curves_served = 0

    # -- faults ------------------------------------------------------------------------
    def inject(self, fault: str, count: int = 1) -> None:
        """The next ``count`` occasions of ``fault`` (one of :data:`FAULTS`) misbehave."""
        if fault not in FAULTS:
            raise ValueError(f"fault: {fault!r} is not one of {', '.join(FAULTS)}")
        with self.lock:
            self.faults[fault] += count

    def _take(self, fault: str) -> bool:
        if self.faults[fault] > 0:
            self.faults[fault] -= 1
            return True
        return False

    # -- derived settings ----------------------------------------------------------------
    @property
    def sample_rate_hz(self) -> float:
        """The rate the record length and horizontal scale (10 divisions) ask for, at most 5 GS/s."""
        return min(MAX_SAMPLE_RATE_HZ, self.record_length / (10.0 * self.horizontal_scale_s))

    def _codes_per_div(self) -> float:
        return CODES_PER_DIV * (256.0 if self.data_width == 2 else 1.0)

    # -- SCPI ----------------------------------------------------------------------------
    def handle(self, line: str) -> list:
        """Answers to one line of program messages (``;``-separated; a header without a leading
        ``:`` after the first continues the previous one's path, as IEEE 488.2 says). Each answer
        is ``str`` (a response line), ``bytes`` (a block) or a fault action (``("fault", name,
        payload)``) for the server."""
        out: list = []
        path: list[str] = []
        for raw in line.split(";"):
            cmd = raw.strip()
            if not cmd:
                continue
            head, _, arg = cmd.partition(" ")
            query = head.endswith("?")
            head = head.rstrip("?")
            if head.startswith("*"):
                nodes = [head.upper()]
            else:
                parts = [_canon(p) for p in head.lstrip(":").split(":")]
                nodes = parts if head.startswith(":") or not path else path[:-1] + parts
                path = nodes
            try:
                ans = self._dispatch(nodes, query, arg.strip())
            except (ValueError, KeyError, IndexError):
                self.esr |= 16
                self.events.append(f'-224,"Illegal parameter value; {cmd}"')
                continue
            if ans is _UNKNOWN:
                self.esr |= 32
                self.events.append(f'-113,"Undefined header; Command not found; {cmd}"')
            elif ans is not None:
                if isinstance(ans, str) and self.header and query and not nodes[0].startswith("*"):
                    ans = ":" + ":".join(nodes) + " " + ans
                out.append(ans)
        # one response message: text answers joined by ';', a block or fault stands alone
        texts = [a for a in out if isinstance(a, str)]
        rest = [a for a in out if not isinstance(a, str)]
        return ([";".join(texts)] if texts else []) + rest

    #: settings that take one of a few mnemonics: the attribute that holds it, and the values
    _CHOICES = {"ROSC:SOURCE": ("reference", ("EXTERNAL", "INTERNAL")),
                "ACQUIRE:MODE": ("acquire_mode", ("SAMPLE", "HIRES")),
                "ACQUIRE:STOPAFTER": ("stop_after", ("SEQUENCE", "RUNSTOP")),
                "DATA:ENCDG": ("data_encoding", ("RIBINARY", "SRIBINARY"))}

    def _dispatch(self, n: list[str], q: bool, arg: str):
        key = ":".join(n)
        if key in self._CHOICES:
            attr, values = self._CHOICES[key]
            if q:
                return getattr(self, attr)
            value = _canon(arg)
            if value not in values:
                raise KeyError(arg)  # answered as a command error, as every bad argument
            setattr(self, attr, value)
            return None
        ch = n[0] if n[0].startswith("CH") and len(n[0]) == 3 else None
        if key == "*IDN":
            return IDN
        if key == "*CLS":
            self.esr, self.events = 0, []
            return None
        if key == "*ESR":
            v, self.esr = self.esr, 0
            return str(v)
        if key == "*OPC":
            return "1" if q else None
        if key == "ALLEV" or key == "EVENT":
            ev, self.events = self.events, []
            return ",".join(ev) if ev else '0,"No events to report - queue empty"'
        if key == "HEADER":
            if q:
                return "1" if self.header else "0"
            self.header = _onoff(arg)
            return None
        if key == "VERBOSE":
            return "1" if q else None
        if key == "ROSC:STATE" and q:
            if self.reference == "INTERNAL":
                return "LOCKED"
            unlocked = self._take("unlocked") or not self.locked_external
            return "UNLOCKED" if unlocked else "LOCKED"
        if key == "HORIZONTAL:RECORDLENGTH":
            if q:
                return str(self.record_length)
            v = int(float(arg))
            if v not in RECORD_LENGTHS:
                raise ValueError(arg)
            self.record_length = v
            return None
        if key == "HORIZONTAL:SCALE":
            if q:
                return f"{self.horizontal_scale_s:.6E}"
            v = _float(arg)
            if not 1e-9 <= v <= 1000:
                raise ValueError(arg)
            self.horizontal_scale_s = v
            return None
        if key == "HORIZONTAL:SAMPLERATE" and q:
            return f"{self.sample_rate_hz:.6E}"
        if key.startswith("SELECT:CH") and len(n) == 2:
            if q:
                return "1" if self.channels[n[1]].on else "0"
            self.channels[n[1]].on = _onoff(arg)
            return None
        if ch is not None and len(n) == 2:
            c = self.channels[ch]
            attr = {"SCALE": "scale_v", "OFFSET": "offset_v", "POSITION": "position_div"}.get(n[1])
            if attr is not None:
                if q:
                    return f"{getattr(c, attr):.6E}"
                v = _float(arg)
                if attr == "scale_v" and not 1e-3 <= v <= 10:
                    raise ValueError(arg)
                if attr == "position_div" and not -5 <= v <= 5:
                    raise ValueError(arg)
                setattr(c, attr, v)
                return None
            if n[1] == "COUPLING":
                if q:
                    return c.coupling
                c.coupling = {"DC": "DC", "AC": "AC"}[_canon(arg)]
                return None
            if n[1] == "TERMINATION":
                if q:
                    return c.termination
                a = _canon(arg)
                c.termination = "FIFTY" if a in ("FIFTY", "50", "5.0E+1") else "MEG" if a in ("MEG", "1.0E+6") \
                    else {"": ""}[a]
                return None
        if key == "TRIGGER:A:EDGE:SOURCE":
            if q:
                return self.trigger_source
            a = _canon(arg)
            if a not in ("AUX", "CH1", "CH2", "CH3", "CH4", "LINE"):
                raise ValueError(arg)
            self.trigger_source = a
            return None
        if key == "TRIGGER:A:EDGE:SLOPE":
            return "RISE" if q else None
        if len(n) == 4 and key.startswith("TRIGGER:A:LEVEL:"):
            if n[3] not in ("AUXIN", "CH1", "CH2", "CH3", "CH4"):
                raise ValueError(n[3])
            if q:
                return f"{self.trigger_level_v.get(n[3], 0.0):.6E}"
            self.trigger_level_v[n[3]] = _float(arg)
            return None
        if key == "ACQUIRE:STATE":
            if q:
                return "0"
            if _canon(arg) in ("ON", "RUN", "1"):
                self.numacq = 0
                self._acquire()
                self.numacq = 3 if self._take("missed") else 1
            return None
        if key == "ACQUIRE:NUMACQ" and q:
            return str(self.numacq)
        if key == "DATA:SOURCE":
            if q:
                return self.data_source
            a = _canon(arg)
            if a not in self.channels:
                raise ValueError(arg)
            self.data_source = a
            return None
        if key == "DATA:WIDTH":
            if q:
                return str(self.data_width)
            v = int(arg)
            if v not in (1, 2):
                raise ValueError(arg)
            self.data_width = v
            return None
        if key in ("DATA:START", "DATA:STOP"):
            attr = "data_start" if key == "DATA:START" else "data_stop"
            if q:
                return str(getattr(self, attr))
            v = int(float(arg))
            if v < 1:
                raise ValueError(arg)
            setattr(self, attr, v)
            return None
        if n[0] == "WFMOUTPRE" and len(n) == 2 and q:
            return self._preamble(n[1])
        if key == "CURVE" and q:
            return self._curve()
        return _UNKNOWN

    # -- acquisitions --------------------------------------------------------------------
    def _acquire(self) -> None:
        fs = self.sample_rate_hz * (0.5 if self._take("sample_rate") else 1.0)
        rl = self.record_length // (2 if self._take("record_length") else 1)
        key = (fs, rl)
        if self.pool and len(self._pools.get(key, [])) >= self.pool:
            pool = self._pools[key]
            self._acq = pool[self._pool_next % len(pool)]
            self._pool_next += 1
            return
        if key not in self._sims:
            sc = scene_variant(self.scene, digitizer={"sample_rate_hz": fs, "samples": max(rl, 256),
                                                      "adc_bits": None, "full_scale_v": None})
            self._sims[key] = Simulator(sc, self.seed)
        fr = self._sims[key].next_frame()
        # pd (or i, q) first, then pulse_ref: CH1, CH2, ... in the simulator's channel order
        volts = {f"CH{i + 1}": np.asarray(fr.volts(name)[:rl], dtype=np.float64) for i, name in enumerate(fr.channels)}
        self._acq = _Acquisition(volts, fs, rl)
        if self.pool:
            self._pools.setdefault(key, []).append(self._acq)

    def _scaling(self) -> tuple[float, float, float]:
        """(YMUlt, YOFf, YZEro) of the data source at the data width."""
        c = self.channels[self.data_source]
        cpd = self._codes_per_div()
        return c.scale_v / cpd, c.position_div * cpd, c.offset_v

    def _preamble(self, item: str) -> str:
        acq = self._acq
        n = 0 if acq is None else max(0, min(acq.record_length, self.data_stop) - self.data_start + 1)
        ymult, yoff, yzero = self._scaling()
        fs = self.sample_rate_hz if acq is None else acq.fs_hz
        return {
            "NR_PT": str(n), "YMULT": f"{ymult:.6E}", "YOFF": f"{yoff:.6E}", "YZERO": f"{yzero:.6E}",
            "XINCR": f"{1.0 / fs:.6E}", "XZERO": f"{-0.5 * (acq.record_length if acq else 0) / fs:.6E}",
            "BYT_NR": str(self.data_width), "BN_FMT": "RI",
            "BYT_OR": "LSB" if self.data_encoding == "SRIBINARY" else "MSB", "ENCDG": "BINARY",
        }[item]

    def codes(self) -> np.ndarray:
        """The data source's samples of the last acquisition as the ADC gives them (int8 or
        int16, shape (NR_Pt,)): 8-bit in SAMPLE mode (shifted up a byte at width 2), 16-bit in
        HIRES mode."""
        acq = self._acq
        if acq is None or self.data_source not in acq.volts:
            raise ValueError("no acquisition of " + self.data_source)
        v = acq.volts[self.data_source][self.data_start - 1: min(acq.record_length, self.data_stop)]
        ymult, yoff, yzero = self._scaling()
        code = (v - yzero) / ymult + yoff
        if self.data_width == 1:
            return np.clip(np.rint(code), -128, 127).astype(np.int8)
        if self.acquire_mode == "SAMPLE":  # an 8-bit ADC: whole steps of 256 codes
            return (np.clip(np.rint(code / 256.0), -128, 127) * 256).astype(np.int16)
        return np.clip(np.rint(code), -32768, 32767).astype(np.int16)

    def _curve(self):
        big = self.data_encoding == "RIBINARY"
        key = (id(self._acq), self.data_source, self.data_width, big, self._scaling(), self.data_start,
               self.data_stop, self.acquire_mode)
        self.curves_served += 1
        short = self._take("short_block")
        block = self._blocks.get(key) if self.pool and not short else None
        if block is None:
            codes = self.codes()
            data = codes.astype(">i2" if big else "<i2") if self.data_width == 2 else codes
            if short:
                data = data[: max(1, data.size - max(1, data.size // 10))]
            block = to_ieee_block(data, datatype="b" if self.data_width == 1 else "h", is_big_endian=big) + b"\n"
            if self.pool and not short:
                self._blocks[key] = block
        for fault in ("timeout", "gone", "truncated"):
            if self._take(fault):
                return ("fault", fault, block)
        if self._take("garbled"):
            return b"#X" + block[2:]
        return block


class _Unknown:
    pass


_UNKNOWN = _Unknown()


def _onoff(arg: str) -> bool:
    a = _canon(arg)
    if a in ("ON", "1"):
        return True
    if a in ("OFF", "0"):
        return False
    raise ValueError(arg)


class ScopeSimServer:
    """Serves a :class:`SimulatedMdo3` as a raw-socket SCPI server (``\\n``-terminated) on 127.0.0.1.

    Parameters
    ----------
    instrument : SimulatedMdo3
    port : int
        0 = a free port; :attr:`resource` names the VISA resource to open.
    down_s : float
        How long the instrument refuses connections after a ``gone`` fault.
    """

    def __init__(self, instrument: SimulatedMdo3, port: int = 0, down_s: float = 0.5) -> None:
        self.instrument = instrument
        self.down_s = down_s
        self._stop = threading.Event()
        self._conns: set[socket.socket] = set()
        self._listener = self._listen(port)
        self.port = self._listener.getsockname()[1]
        self._thread = threading.Thread(target=self._accept_loop, name="scope-sim", daemon=True)
        self._thread.start()

    @property
    def resource(self) -> str:
        """The VISA resource string of the instrument (for ``pyvisa-py``)."""
        return f"TCPIP0::127.0.0.1::{self.port}::SOCKET"

    @staticmethod
    def _listen(port: int) -> socket.socket:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))
        s.listen(4)
        s.settimeout(0.1)
        return s

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except socket.timeout:
                continue
            except OSError:  # the listener was closed (gone, or stopping)
                if self._stop.wait(0.02):
                    return
                continue
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._conns.add(conn)
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        buf = b""
        try:
            while not self._stop.is_set():
                chunk = conn.recv(65536)
                if not chunk:
                    return
                buf += chunk
                while b"\n" in buf:
                    line, _, buf = buf.partition(b"\n")
                    with self.instrument.lock:
                        answers = self.instrument.handle(line.decode("ascii", "replace"))
                    for ans in answers:
                        if isinstance(ans, str):
                            conn.sendall(ans.encode("ascii") + b"\n")
                        elif isinstance(ans, bytes):
                            conn.sendall(ans)
                        else:
                            self._fault(conn, ans[1], ans[2])
        except OSError:
            return
        finally:
            self._conns.discard(conn)
            try:
                conn.close()
            except OSError:
                pass

    def _fault(self, conn: socket.socket, fault: str, block: bytes) -> None:
        log.info("scope-sim: fault %s", fault)
        if fault == "timeout":
            return  # never answered
        if fault == "truncated":
            conn.sendall(block[: len(block) // 2])
            return
        if fault == "gone":
            conn.sendall(block[: len(block) // 2])
            self._go_down()
            raise OSError("gone")

    def _go_down(self) -> None:
        """Close every connection and refuse new ones for :attr:`down_s` seconds."""
        try:  # stops listening at once, even while the accept thread waits on it
            self._listener.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._listener.close()
        for c in list(self._conns):
            try:
                c.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

        def back() -> None:
            if not self._stop.wait(self.down_s):
                self._listener = self._listen(self.port)

        threading.Thread(target=back, daemon=True).start()

    def close(self) -> None:
        self._stop.set()
        try:
            self._listener.close()
        except OSError:
            pass
        for c in list(self._conns):
            try:
                c.close()
            except OSError:
                pass
        self._thread.join(timeout=2)

    def __enter__(self) -> "ScopeSimServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def autoset(scene: Scene, record_length: int, sample_rate_hz: float, seed: Optional[int] = None,
            divisions: float = 8.0) -> dict[str, tuple[float, float]]:
    """Vertical (scale V/div, offset V) per channel that puts one simulated frame of ``scene``
    within ``divisions`` divisions around the screen's centre, as a person would set the scope
    (the ADC spans about 10.2)."""
    sc = scene_variant(scene, digitizer={"sample_rate_hz": sample_rate_hz, "samples": max(record_length, 256),
                                         "adc_bits": None, "full_scale_v": None})
    fr = Simulator(sc, seed).frame(0)
    out = {}
    for name in fr.channels:
        v = fr.volts(name)
        lo, hi = float(v.min()), float(v.max())
        span = max(hi - lo, 1e-6)
        out[name] = (span / divisions, 0.5 * (hi + lo))
    return out


def sim_settings(settings, scene: Scene) -> dict:
    """The scope settings ``scope-sim`` takes from the scene when they are unset: the tone plan,
    wavelength, receiver, gate timing and reference-pulse channel of the bench, its sample rate,
    the longest record length of the scope within the scene's samples, and the trigger on AUX."""
    iq = scene.receiver.kind == "iq"
    pulsed = scene.pulsing is not None
    rl = settings.record_length or max([r for r in RECORD_LENGTHS if r <= scene.digitizer.samples] or [1000])
    up = {
        "tones_hz": settings.tones_hz or list(scene.tones_hz),
        "wavelength_m": settings.wavelength_m or scene.laser.wavelength_m,
        "receiver": settings.receiver or scene.receiver.kind,
        "record_length": rl,
        "sample_rate_hz": settings.sample_rate_hz or scene.digitizer.sample_rate_hz,
        "trigger_source": settings.trigger_source or "AUX",
        "visa_library": "@py",
    }
    if pulsed and settings.pulse_period_s is None:
        up.update(pulse_period_s=scene.pulsing.period_s, pulse_duty=scene.pulsing.duty,
                  pulse_delay_s=scene.pulsing.delay_s)
    if pulsed and scene.pulsing.reference_channel and settings.scope_pulse_ref_channel is None:
        up["scope_pulse_ref_channel"] = "CH3" if iq else "CH2"
    return up


class SimulatedScopeSource(ScopeSource):
    """Source ``scope-sim``: the scope source against a :class:`SimulatedMdo3` of ``settings.scene``
    served on a free port of 127.0.0.1 (through PyVISA and pyvisa-py, as a real scope). Unset
    scope settings come from the scene (:func:`sim_settings`); the vertical scale and offset,
    unless given, are fitted to the scene's signal (:func:`autoset`)."""

    def __init__(self, settings, stop: Optional[threading.Event] = None,
                 on_error: Optional[Callable[[str], None]] = None,
                 on_missed: Optional[Callable[[int], None]] = None) -> None:
        scene = load_scene(settings.scene)
        settings = settings.model_copy(update=sim_settings(settings, scene))
        cfg = scope_config(settings.model_copy(update={"scope_channels": settings.scope_channels or (
            ["CH1", "CH2"] if settings.receiver == "iq" else ["CH1"])}))
        if settings.vertical_scale_v is None:
            fitted = autoset(scene, settings.record_length, settings.sample_rate_hz, settings.seed)
            cfg = _replace(cfg, vertical=tuple(fitted.values())[: len(cfg.channels)])
        self.instrument = SimulatedMdo3(scene, settings.seed, pool=settings.scope_sim_pool)
        self.server = ScopeSimServer(self.instrument)
        log.info("scope-sim: a simulated MDO3 of scene %s at %s", scene.name, self.server.resource)
        super().__init__(settings, stop=stop, on_error=on_error, on_missed=on_missed, config=cfg,
                         resource=self.server.resource)

    def close(self) -> None:
        super().close()
        self.server.close()


def _replace(cfg, **kw):
    from dataclasses import replace

    return replace(cfg, **kw)
