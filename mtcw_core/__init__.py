"""mtcw_core: pure computation for multi-tone CW lidar (simulation, DSP, ranging).

Never imports transport or web code (zmq, msgpack, fastapi, uvicorn, prometheus_client).
"""

__version__ = "0.1.0"
