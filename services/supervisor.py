"""``mtcw run``: acquisition node, worker(s) and API as child processes on loopback.

Each service is its own process (``python -m services.cli <service>``): a worker's chain runs
without the GIL of the others, and each stops on SIGTERM as in a real deployment. The
supervisor forwards Ctrl-C / SIGTERM, waits for the children, and kills what does not stop.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field


def free_ports(n: int) -> list[int]:
    """``n`` TCP ports free on loopback right now (for tests and benchmarks on one machine)."""
    socks = [socket.socket() for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def free_port_block(n: int, tries: int = 50) -> int:
    """A port ``p`` such that ``p .. p + n - 1`` are all free on loopback right now (``mtcw run
    --base-port`` takes consecutive ports)."""
    for _ in range(tries):
        base = free_ports(1)[0]
        if base + n > 65535:
            continue
        socks = []
        try:
            for q in range(base, base + n):
                s = socket.socket()
                socks.append(s)
                s.bind(("127.0.0.1", q))
            return base
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    raise RuntimeError(f"no {n} consecutive free ports found")


@dataclass
class Child:
    name: str
    argv: list[str]
    proc: subprocess.Popen | None = None


@dataclass
class Supervisor:
    children: list[Child] = field(default_factory=list)
    env: dict[str, str] = field(default_factory=dict)
    stop_timeout_s: float = 8.0

    def add(self, name: str, *args: str) -> None:
        self.children.append(Child(name, [sys.executable, "-m", "services.cli", *args]))

    def start(self) -> None:
        env = {**os.environ, **self.env}
        for c in self.children:
            c.proc = subprocess.Popen(c.argv, env=env)

    def alive(self) -> list[str]:
        return [c.name for c in self.children if c.proc is not None and c.proc.poll() is None]

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
                c.proc.kill()
                codes[c.name] = c.proc.wait()
        return {c.name: codes[c.name] for c in self.children if c.name in codes}

    def run_until_signal(self, on_tick=None) -> dict[str, int]:
        """Start, then wait for SIGINT/SIGTERM or a child's death; stop everything."""
        stopping = {"why": None}

        def handler(signum, _frame):
            stopping["why"] = signal.Signals(signum).name

        old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            self.start()
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
