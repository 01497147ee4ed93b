"""The scope source (services/sources/scope.py): the control plane against the pyvisa-sim
definition shipped with mtcw, the waveform path and every fault against the simulated MDO3
(services/sources/scope_sim.py) through PyVISA and pyvisa-py over a loopback socket.

The frames' volts are checked against the physics simulator's volts of the same acquisition
(held by the simulated instrument, never sent), not against numbers the driver printed.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from services.settings import AcquisitionSettings, load
from services.sources.scope import REASONS, Mdo3, ScopeConfig, ScopeError, ScopeSource, sim_definition
from services.sources.scope_sim import ScopeSimServer, SimulatedMdo3, autoset

from .conftest import make_scene

TONES = [500e6, 700e6, 950e6]
RL = 10_000


# -- the control plane against pyvisa-sim ---------------------------------------------------------
def _sim(resource: str = "TCPIP::mdo34-sim::INSTR") -> Mdo3:
    m = Mdo3(resource, "sim", timeout_s=1.0)
    m.open()
    return m


def test_control_plane_sets_what_is_asked_and_reads_it_back():
    m = _sim()
    try:
        assert m.idn.startswith("TEKTRONIX,MDO34")
        got = m.configure(ScopeConfig(record_length=100_000, sample_rate_hz=5e9, vertical=((0.05, 0.3),),
                                      trigger_source="AUX", trigger_level_v=0.7, termination="FIFTY", data_width=1))
        assert got["record_length"] == 100_000 and got["sample_rate_hz"] == 5e9
        assert got["reference"] == "EXTERNAL" and got["trigger_source"] == "AUX"
        assert got["channels"] == {"CH1": {"scale_v_per_div": 0.05, "offset_v": 0.3}}
        assert got["data_width"] == 1 and got["encoding"] == "SRIBINARY"
        # the horizontal scale asked is record length / (10 divisions x fs)
        assert m.query_float("HORIZONTAL:SCALE?") == pytest.approx(100_000 / (10 * 5e9))
        assert m.query_float("TRIGGER:A:LEVEL:AUXIN?") == 0.7 and m.query("CH1:TERMINATION?") == "FIFTY"
    finally:
        m.close()


def test_control_plane_refuses_an_unlocked_reference():
    m = _sim("TCPIP::mdo34-unlocked::INSTR")
    try:
        with pytest.raises(ScopeError, match="not locked to the external 10 MHz") as err:
            m.configure(ScopeConfig(record_length=100_000))
        assert err.value.reason == "reference_unlocked"
        m.configure(ScopeConfig(record_length=100_000, external_reference=False))  # internal: no lock needed
    finally:
        m.close()


def test_control_plane_names_a_rate_the_scope_did_not_take_and_a_refused_setting():
    m = _sim()
    try:
        with pytest.raises(ScopeError, match=r"asked for 2\.5e\+09 S/s.*5e\+09") as err:
            m.configure(ScopeConfig(record_length=100_000, sample_rate_hz=2.5e9))
        assert err.value.reason == "sample_rate"
        with pytest.raises(ScopeError, match="refused a command") as err:
            m.configure(ScopeConfig(vertical=((50.0, 0.0),)))  # 50 V/div: beyond the definition's specs
        assert err.value.reason == "instrument_error"
    finally:
        m.close()


def test_unreachable_resource_is_a_connection_error():
    m = Mdo3("TCPIP::127.0.0.1::1::SOCKET", "@py", timeout_s=0.5)  # nothing listens on port 1
    with pytest.raises(ScopeError) as err:
        m.open()
    assert err.value.reason == "connection"
    assert sim_definition().endswith("mdo3.yaml")


# -- the waveform path against the simulated MDO3 ---------------------------------------------------
class RecordingStop(threading.Event):
    """A stop event that records the back-off waits instead of sleeping them out."""

    def __init__(self) -> None:
        super().__init__()
        self.waits: list[float] = []

    def wait(self, timeout=None) -> bool:
        self.waits.append(timeout)
        return self.is_set()


@pytest.fixture(scope="module")
def scene():
    return make_scene(digitizer={"samples": 2**14}, noise={"shot": True, "thermal": True})


@pytest.fixture
def instrument(scene):
    inst = SimulatedMdo3(scene, seed=5)
    with ScopeSimServer(inst, down_s=0.2) as srv:
        inst.server = srv
        yield inst


def _settings(resource: str, scene, **over) -> AcquisitionSettings:
    scale, offset = next(iter(autoset(scene, RL, 5e9, seed=5).values()))
    kw = dict(source="scope", resource=resource, tones_hz=",".join(str(t) for t in TONES),
              wavelength_m=1.064e-6, record_length=RL, sample_rate_hz=5e9, vertical_scale_v=scale,
              vertical_offset_v=offset, trigger_source="AUX", visa_timeout_s=0.5, retry_backoff_s=0.01,
              retry_backoff_max_s=0.04)
    kw.update(over)
    return load(AcquisitionSettings, **kw)


@pytest.mark.parametrize("width,encoding", [(1, "SRIBINARY"), (2, "SRIBINARY"), (2, "RIBINARY")])
def test_frames_carry_the_scopes_codes_scaled_to_the_simulated_volts(instrument, scene, width, encoding):
    src = ScopeSource(_settings(instrument.server.resource, scene, data_width=width, data_encoding=encoding,
                                visa_chunk_bytes=4096))  # records of 10-20 kB: read in several chunks
    try:
        fr = next(src.frames())
    finally:
        src.close()
    assert fr.samples.shape == (1, RL) and fr.samples.dtype == (np.int8 if width == 1 else np.dtype("<i2"))
    assert fr.fs_hz == pytest.approx(5e9) and fr.tones_hz == tuple(TONES) and fr.wavelength_m == 1.064e-6
    assert fr.channels == ("pd",) and fr.receiver == "single"
    truth = instrument._acq.volts["CH1"]
    step = instrument.channels["CH1"].scale_v / 25  # one 8-bit ADC code
    assert np.max(np.abs(fr.volts("pd") - truth)) <= 0.5 * step * (1 + 1e-6)
    assert src.in_force["record_length"] == RL and src.errors == {}


def test_chunk_size_does_not_change_the_data(instrument, scene):
    out = []
    for chunk in (1024, 1 << 20):
        inst2 = SimulatedMdo3(scene, seed=9)
        with ScopeSimServer(inst2) as srv:
            src = ScopeSource(_settings(srv.resource, scene, visa_chunk_bytes=chunk))
            out.append(next(src.frames()).samples.copy())
            src.close()
    assert np.array_equal(out[0], out[1])


@pytest.mark.parametrize("fault,reason", [
    ("timeout", "timeout"), ("gone", "transfer_incomplete"), ("truncated", "transfer_incomplete"),
    ("garbled", "garbled_block"), ("short_block", "block_size"), ("record_length", "record_length"),
    ("sample_rate", "sample_rate"), ("unlocked", "reference_unlocked")])
def test_each_fault_is_named_counted_retried_and_never_a_frame(instrument, scene, fault, reason):
    stop = RecordingStop()
    counted: list[str] = []
    src = ScopeSource(_settings(instrument.server.resource, scene), stop=stop, on_error=counted.append)
    frames = src.frames()
    first = next(frames)
    instrument.inject(fault, count=2)
    second = next(frames)  # two failures, then a good frame
    src.close()
    assert counted == [reason, reason] and src.errors == {reason: 2}
    assert stop.waits == [0.01, 0.02]  # back-off doubles
    for fr in (first, second):  # only whole, right-rate frames are yielded
        assert fr.samples.shape == (1, RL) and fr.fs_hz == pytest.approx(5e9)
    assert np.max(np.abs(second.volts("pd") - instrument._acq.volts["CH1"])) <= 0.5 * instrument.channels[
        "CH1"].scale_v / 25 * (1 + 1e-6)


def test_instrument_gone_for_a_while_is_a_connection_error_until_it_is_back(instrument, scene):
    instrument.server.down_s = 1.5
    stop = RecordingStop()
    src = ScopeSource(_settings(instrument.server.resource, scene, retry_backoff_s=0.2, retry_backoff_max_s=0.2),
                      stop=stop)
    stop.wait = lambda timeout=None: (stop.waits.append(timeout), threading.Event().wait(timeout))[1]
    frames = src.frames()
    next(frames)
    instrument.inject("gone")
    fr = next(frames)
    src.close()
    assert src.errors["transfer_incomplete"] == 1 and src.errors.get("connection", 0) >= 1
    assert fr.samples.shape == (1, RL)


def test_missed_acquisitions_are_counted(instrument, scene):
    missed: list[int] = []
    src = ScopeSource(_settings(instrument.server.resource, scene), on_missed=missed.append)
    frames = src.frames()
    next(frames)
    instrument.inject("missed")
    next(frames)
    src.close()
    assert missed == [2] and src.missed == 2


def test_gives_up_after_max_failures_naming_the_cause(instrument, scene):
    instrument.locked_external = False
    src = ScopeSource(_settings(instrument.server.resource, scene, scope_max_failures=3), stop=RecordingStop())
    with pytest.raises(ScopeError, match="not locked") as err:
        next(src.frames())
    assert err.value.reason == "reference_unlocked" and src.errors == {"reference_unlocked": 3}


def test_iq_and_reference_pulse_channels_map_to_frame_channels(scene):
    sc = make_scene(digitizer={"samples": 2**14}, receiver={"kind": "iq"})
    inst = SimulatedMdo3(sc, seed=1)
    fitted = list(autoset(sc, RL, 5e9, seed=1).values())
    with ScopeSimServer(inst) as srv:
        st = _settings(srv.resource, sc, receiver="iq")
        cfg = ScopeConfig(channels=("CH1", "CH2"), record_length=RL, sample_rate_hz=5e9, vertical=tuple(fitted))
        src = ScopeSource(st, config=cfg)
        fr = next(src.frames())
        src.close()
    assert fr.channels == ("i", "q") and fr.receiver == "iq"
    # the channels are scaled differently: they travel as float32 volts
    assert fr.samples.dtype == np.float32 and fr.scale == 1.0
    for name, ch in (("i", "CH1"), ("q", "CH2")):
        assert np.max(np.abs(fr.volts(name) - inst._acq.volts[ch])) <= 0.5 * inst.channels[ch].scale_v / 25 * 1.001


def test_reasons_are_the_metric_labels():
    assert len(set(REASONS)) == len(REASONS) and "reference_unlocked" in REASONS
    with pytest.raises(AssertionError):
        ScopeError("no_such_reason", "x")
