"""Transfer rate of the scope path: MB/s and frames/s of single-sequence acquisitions.

Each frame is what the scope source does per frame (:meth:`services.sources.scope.ScopeSource.read_frame`
without the frame object): check the reference lock, ``ACQuire:STATE ON`` + ``*OPC?``,
``ACQuire:NUMACq?``, ``WFMOutpre`` and ``CURVe?`` read in chunks. ``MB/s`` is the block bytes
over the time spent in ``CURVe?`` alone (10^6 bytes per MB); ``frames/s`` counts the whole
frame. Without ``resource`` the instrument is the simulated MDO3
(:mod:`services.sources.scope_sim`) on 127.0.0.1 through PyVISA and pyvisa-py, with its
acquisitions pooled (two simulated, then repeated) so that the numbers are the VISA path's, not
the physics simulator's.

Run: ``mtcw scope bench`` (``--record-length 1000000 --width 1 --width 2 --frames 20``), or
``--resource TCPIP::host::INSTR`` against a real scope.
"""

from __future__ import annotations

import time
from typing import Optional

from mtcw_core.scene import load_scene
from services.sources.scope import Mdo3, ScopeConfig


def bench_transfer(record_length: int = 1_000_000, widths: tuple[int, ...] = (1, 2), frames: int = 20,
                   resource: Optional[str] = None, visa_library: str = "@py", scene: str = "cw-bench",
                   sample_rate_hz: float = 5e9, timeout_s: float = 20.0,
                   external_reference: bool = True) -> list[dict]:
    """Measure ``frames`` acquisitions per data width.

    Returns
    -------
    list of dict
        One per width: ``data_width``, ``record_length``, ``frames``, ``bytes_per_frame``,
        ``transfer_mb_per_s``, ``frames_per_s``, ``transfer_s_median``, ``frame_s_median``.
    """
    import statistics

    server = None
    if resource is None:
        from services.sources.scope_sim import ScopeSimServer, SimulatedMdo3, autoset

        sc = load_scene(scene)
        server = ScopeSimServer(SimulatedMdo3(sc, seed=1, pool=2))
        resource, visa_library = server.resource, "@py"
        vertical = tuple(autoset(sc, record_length, sample_rate_hz, seed=1).values())[:1]
    else:
        vertical = None
    out = []
    try:
        for width in widths:
            scope = Mdo3(resource, visa_library, timeout_s)
            scope.open()
            try:
                cfg = ScopeConfig(channels=("CH1",), record_length=record_length, sample_rate_hz=sample_rate_hz,
                                  vertical=vertical, data_width=width, external_reference=external_reference)
                scope.configure(cfg)
                t_frame, t_curve = [], []
                for i in range(frames + 2):  # two to warm up (the simulator's pool, the connection)
                    t0 = time.perf_counter()
                    if external_reference:
                        scope.check_reference()
                    scope.acquire()
                    t1 = time.perf_counter()
                    wf = scope.read_waveform("CH1", record_length)
                    t2 = time.perf_counter()
                    if i >= 2:
                        t_frame.append(t2 - t0)
                        t_curve.append(t2 - t1)
                    assert wf.codes.size == record_length
            finally:
                scope.close()
            nbytes = record_length * width
            out.append({"data_width": width, "record_length": record_length, "frames": frames,
                        "bytes_per_frame": nbytes,
                        "transfer_mb_per_s": round(nbytes * frames / sum(t_curve) / 1e6, 1),
                        "frames_per_s": round(frames / sum(t_frame), 2),
                        "transfer_s_median": round(statistics.median(t_curve), 4),
                        "frame_s_median": round(statistics.median(t_frame), 4)})
    finally:
        if server is not None:
            server.close()
    return out
