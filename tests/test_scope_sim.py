"""The simulated MDO3 (services/sources/scope_sim.py) on its own: SCPI, blocks, scaling, faults.

Truth here is independent of the driver: blocks are decoded with PyVISA's own
``from_ieee_block``, and codes are turned back into volts with the WFMOutpre formula a Tek
programmer manual gives, then compared with the physics simulator's volts of the same
acquisition (to half a code step).
"""

from __future__ import annotations

import socket

import numpy as np
import pytest
from pyvisa.util import from_ieee_block

from services.sources.scope_sim import (FAULTS, RECORD_LENGTHS, ScopeSimServer, SimulatedMdo3, _canon, autoset)

from .conftest import make_scene


@pytest.fixture
def scope() -> SimulatedMdo3:
    sc = make_scene(digitizer={"samples": 2**14}, noise={"shot": True, "thermal": True})
    s = SimulatedMdo3(sc, seed=3)
    s.handle("HEADER OFF")
    s.handle("HORIZONTAL:RECORDLENGTH 10000;:HORIZONTAL:SCALE 2E-7")
    (scale, offset), = autoset(sc, 10_000, 5e9, seed=3).values()
    s.handle(f"CH1:SCALE {scale:.6E};OFFSET {offset:.6E}")
    return s


def test_mnemonics_short_long_and_between_forms():
    assert _canon("hor") == _canon("HORizontal") == _canon("HORIZ") == "HORIZONTAL"
    assert _canon("STOP") == "STOP" and _canon("STOPA") == "STOPAFTER" and _canon("AUX") == "AUX"
    assert _canon("ch2") == "CH2" and _canon("wfmo") == "WFMOUTPRE"


def test_queries_settings_and_compound_messages(scope):
    assert scope.handle("*IDN?")[0].startswith("TEKTRONIX,MDO34")
    assert scope.handle("hor:reco?") == ["10000"]
    # 10 divisions: fs = record length / (10 x s/div)
    assert float(scope.handle("HORizontal:SAMPLERate?")[0]) == pytest.approx(10_000 / (10 * 2e-7))
    scope.handle("HORIZONTAL:SCALE 1E-9")
    assert float(scope.handle("HORIZONTAL:SAMPLERATE?")[0]) == 5e9  # capped at the MDO3's 5 GS/s
    # a header without ':' continues the previous path; ';' joins the answers of one message
    assert scope.handle("DATA:WIDTH 2;ENCDG SRIBINARY;WIDTH?;ENCDG?") == ["2;SRIBINARY"]
    scope.handle("HEADER ON")
    assert scope.handle("DATA:WIDTH?") == [":DATA:WIDTH 2"]


def test_errors_are_flagged_in_esr_and_the_event_queue(scope):
    assert scope.handle("*ESR?") == ["0"]
    scope.handle("FOO:BAR 1")
    scope.handle("HORIZONTAL:RECORDLENGTH 12345")  # not a record length of the scope
    assert int(scope.handle("*ESR?")[0]) == 32 | 16
    events = scope.handle("ALLEV?")[0]
    assert "Undefined header" in events and "RECORDLENGTH 12345" in events
    assert scope.handle("HORIZONTAL:RECORDLENGTH?") == ["10000"] and scope.record_length in RECORD_LENGTHS


@pytest.mark.parametrize("width,encoding", [(1, "RIBINARY"), (2, "RIBINARY"), (2, "SRIBINARY")])
def test_curve_is_an_ieee_block_whose_codes_scale_back_to_the_simulated_volts(scope, width, encoding):
    scope.handle(f"DATA:SOURCE CH1;WIDTH {width};ENCDG {encoding}")
    scope.handle("ACQUIRE:STOPAFTER SEQUENCE;STATE ON")
    assert scope.handle("ACQUIRE:NUMACQ?") == ["1"]
    pre = scope.handle("WFMOUTPRE:NR_PT?;YMULT?;YOFF?;YZERO?;XINCR?;BYT_OR?")[0].split(";")
    n, ymult, yoff, yzero, xincr = int(pre[0]), *map(float, pre[1:5])
    block = scope.handle("CURVE?")[0]
    assert block.startswith(b"#") and block.endswith(b"\n")
    digits = int(block[1:2])
    assert int(block[2:2 + digits]) == n * width  # the header's byte count
    codes = np.asarray(from_ieee_block(block[:-1], datatype="b" if width == 1 else "h",
                                       is_big_endian=pre[5] == "MSB"))
    assert codes.size == n == 10_000
    volts = (codes - yoff) * ymult + yzero
    truth = scope._acq.volts["CH1"]
    step = ymult * (256 if width == 2 else 1)  # an 8-bit ADC in SAMPLE mode
    assert np.max(np.abs(volts - truth)) <= 0.5 * step * (1 + 1e-6)
    assert ymult == pytest.approx(float(scope.handle("CH1:SCALE?")[0]) / (25 * (256 if width == 2 else 1)))
    assert xincr == pytest.approx(1 / 5e9)
    # the scene's signal fills the screen: an 8-bit ADC uses most of its codes
    assert np.ptp(codes) / (256 if width == 2 else 1) > 150


def test_hires_gives_16_bit_codes(scope):
    scope.handle("ACQUIRE:MODE HIRES;:DATA:WIDTH 2;:ACQUIRE:STATE ON")
    assert np.any(scope.codes() % 256 != 0)
    scope.handle("ACQUIRE:MODE SAMPLE;STATE ON")
    assert np.all(scope.codes() % 256 == 0)


def test_faults_in_the_instrument(scope):
    with pytest.raises(ValueError, match="fault"):
        scope.inject("melted")
    scope.handle("DATA:WIDTH 1;:ACQUIRE:STATE ON")
    scope.inject("garbled")
    assert scope.handle("CURVE?")[0].startswith(b"#X")
    scope.inject("short_block")
    block = scope.handle("CURVE?")[0]
    assert int(block[2:2 + int(block[1:2])]) < 10_000
    for fault in ("timeout", "gone", "truncated"):
        scope.inject(fault)
        assert scope.handle("CURVE?")[0][:2] == ("fault", fault)
    scope.inject("record_length")
    scope.inject("sample_rate")
    scope.inject("missed")
    scope.handle("ACQUIRE:STATE ON")
    assert scope.handle("WFMOUTPRE:NR_PT?;XINCR?;:ACQUIRE:NUMACQ?") == ["5000;4.000000E-10;3"]
    scope.handle("ROSC:SOURCE EXTERNAL")
    scope.inject("unlocked")
    assert scope.handle("ROSC:STATE?") == ["UNLOCKED"] and scope.handle("ROSC:STATE?") == ["LOCKED"]
    assert set(FAULTS) == {"timeout", "gone", "truncated", "garbled", "short_block", "record_length", "sample_rate",
                           "unlocked", "missed"}


def test_server_speaks_scpi_over_a_socket_and_goes_away_when_gone(scope):
    with ScopeSimServer(scope, down_s=3.0) as srv:
        assert srv.resource == f"TCPIP0::127.0.0.1::{srv.port}::SOCKET"
        with socket.create_connection(("127.0.0.1", srv.port), timeout=5) as c:
            c.sendall(b"*IDN?\n")
            assert c.recv(4096).startswith(b"TEKTRONIX,MDO34")
            c.sendall(b"ACQUIRE:STATE ON\n")
            scope.inject("gone")
            c.sendall(b"CURVE?\n")
            got = b""
            while chunk := c.recv(65536):
                got += chunk
            assert got.startswith(b"#") and len(got) < 10_000  # half a block, then the connection closed
        with pytest.raises(OSError):
            socket.create_connection(("127.0.0.1", srv.port), timeout=1).close()
