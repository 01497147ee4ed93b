"""``mtcw run``: acquisition node, worker(s) and API as child processes on loopback.

Each service is its own process (``python -m services.cli <service>``): a worker's chain runs
without the GIL of the others, and each stops on SIGTERM as in a real deployment. Children that
bind (the API, the acquisition node) are started one after the other, each reporting its bound
endpoints to a file (``MTCW_ENDPOINTS_FILE``, :func:`services.sockets.report_endpoints`); the
children started after them get those endpoints in their environment. So the services may bind
to port 0 and nobody guesses a free port. The supervisor forwards Ctrl-C / SIGTERM, waits for
the children, and kills what does not stop.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

from .sockets import wait_for_endpoints

log = logging.getLogger(__name__)


def dump_stacks(proc: subprocess.Popen, wait_s: float = 1.0) -> None:
    """Ask a running service for its threads' Python stacks (SIGUSR1: every ``mtcw`` service
    writes them to its stderr and goes on), and give it ``wait_s`` to write them."""
    if proc.poll() is None and hasattr(signal, "SIGUSR1"):
        proc.send_signal(signal.SIGUSR1)
        time.sleep(wait_s)


def free_ports(n: int) -> list[int]:
    """``n`` TCP ports free on loopback right now, for programs that cannot bind port 0 and report
    what they got (Prometheus in a test, ``bench/stream.py``, the compose test's fixed ports).
    Racy by nature: another process may take a port before it is used."""
    socks = [socket.socket() for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


@dataclass
class Child:
    """One service process.

    Attributes
    ----------
    name : str
    argv : list of str
    env : dict
        Its own environment (over the supervisor's and the endpoints reported before it).
    reports : bool
        It binds and reports its endpoints; the next child starts once they are reported.
    """

    name: str
    argv: list[str]
    env: dict[str, str] = field(default_factory=dict)
    reports: bool = False
    proc: Optional[subprocess.Popen] = None


@dataclass
class Supervisor:
    """Child processes started in order, stopped in reverse order.

    Attributes
    ----------
    env : dict
        Environment of every child (over ``os.environ``).
    endpoints : dict
        What the reporting children reported (``frames_endpoint``, ``points_endpoint``,
        ``http_url``, ...), filled by :meth:`start`.
    """

    children: list[Child] = field(default_factory=list)
    env: dict[str, str] = field(default_factory=dict)
    stop_timeout_s: float = 8.0
    start_timeout_s: float = 60.0
    endpoints: dict[str, str] = field(default_factory=dict)

    def add(self, name: str, *args: str, reports: bool = False, env: Optional[dict[str, str]] = None) -> None:
        self.children.append(Child(name, [sys.executable, "-m", "services.cli", *args], dict(env or {}), reports))

    def start(self) -> None:
        """Start the children in order; after a reporting child, wait for its endpoints.

        Raises
        ------
        TimeoutError
            When a reporting child exits or reports nothing within ``start_timeout_s``.
        """
        tmp = Path(tempfile.mkdtemp(prefix="mtcw-run-"))
        try:
            for c in self.children:
                reported = {f"MTCW_{k.upper()}": v for k, v in self.endpoints.items() if k.endswith("_endpoint")}
                env = {**os.environ, **self.env, **reported, **c.env}
                path = tmp / f"{c.name}.json"
                if c.reports:
                    env["MTCW_ENDPOINTS_FILE"] = str(path)
                c.proc = subprocess.Popen(c.argv, env=env)
                if c.reports:
                    proc = c.proc
                    got = wait_for_endpoints(path, self.start_timeout_s, alive=lambda: proc.poll() is None)
                    self.endpoints.update(got)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def stop(self) -> dict[str, int]:
        """SIGTERM one by one in reverse start order, upstream first (the acquisition node's
        end-of-run notice still finds a worker, and the API is last out so that points still
        land); whatever has not stopped by the deadline is killed."""
        deadline = time.monotonic() + self.stop_timeout_s
        codes = {}
        for c in reversed(self.children):
            if c.proc is None:
                continue
            if c.proc.poll() is None:
                c.proc.send_signal(signal.SIGTERM)
            try:
                codes[c.name] = c.proc.wait(max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                log.error("supervisor: %s did not stop within %.0f s of SIGTERM; its stacks, then SIGKILL",
                          c.name, self.stop_timeout_s)
                dump_stacks(c.proc)
                c.proc.kill()
                codes[c.name] = c.proc.wait()
        return {c.name: codes[c.name] for c in self.children if c.name in codes}

    def run_until_signal(self, on_tick: Optional[Callable[[], None]] = None,
                         on_start: Optional[Callable[["Supervisor"], None]] = None) -> dict[str, int]:
        """Start, then wait for SIGINT/SIGTERM or a child's death; stop everything.

        Returns the children's exit codes, and under ``"_why"`` why it stopped.
        """
        stopping: dict[str, Optional[str]] = {"why": None}

        def handler(signum, _frame):
            stopping["why"] = signal.Signals(signum).name

        old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            try:
                self.start()
            except TimeoutError as err:
                stopping["why"] = f"start failed: {err}"
            if stopping["why"] is None and on_start:
                on_start(self)
            while stopping["why"] is None:
                dead = [c for c in self.children if c.proc.poll() is not None]
                if dead:
                    stopping["why"] = f"{dead[0].name} exited with code {dead[0].proc.returncode}"
                    break
                if on_tick:
                    on_tick()
                time.sleep(0.2)
        finally:
            codes = self.stop()
            for s, h in old.items():
                signal.signal(s, h)
        codes["_why"] = stopping["why"]  # type: ignore[assignment]
        return codes
