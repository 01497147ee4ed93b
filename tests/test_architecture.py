"""The layout as an invariant: the import graph of ``mtcw_core`` has no cycle and no arrow from
``dsp/`` to ``ranging/``; the core never imports transport; the runner stays a runner."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CORE = ROOT / "mtcw_core"
TRANSPORT = {"zmq", "fastapi", "msgpack", "msgspec", "uvicorn", "starlette", "httpx", "prometheus_client"}


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    """Absolute names of every module imported anywhere in the file (lazy imports too)."""
    mod = _module_name(path)
    package = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            out.add(name)
            # `from . import x` / `from .dsp import spectrum` may name submodules
            out |= {f"{name}.{a.name}" for a in node.names}
    return out


def core_graph() -> dict[str, set[str]]:
    files = {_module_name(p): p for p in CORE.rglob("*.py")}
    graph = {}
    for name, path in files.items():
        deps = {d for d in _imports(path) if d in files and d != name}
        graph[name] = deps
    return graph


def test_no_import_cycle_in_core():
    graph = core_graph()
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> None:
        state[n] = 1
        stack.append(n)
        for d in sorted(graph[n]):
            if d.endswith("__init__") or d == "mtcw_core":
                continue
            if state.get(d) == 1:
                pytest.fail("import cycle: " + " -> ".join(stack[stack.index(d):] + [d]))
            if state.get(d) is None:
                visit(d)
        stack.pop()
        state[n] = 2

    for n in sorted(graph):
        if state.get(n) is None:
            visit(n)


def test_dsp_never_imports_ranging():
    bad = [(m, d) for m, deps in core_graph().items() if m.startswith("mtcw_core.dsp")
           for d in deps if d.startswith("mtcw_core.ranging")]
    assert not bad, bad


def test_core_never_imports_transport_or_services():
    for path in CORE.rglob("*.py"):
        roots = {d.split(".")[0] for d in _imports(path)}
        assert not roots & (TRANSPORT | {"services", "mtcw_bench"}), (path, roots & (TRANSPORT | {"services"}))


def test_chain_is_a_runner_and_functions_are_short():
    assert len((CORE / "chain.py").read_text().splitlines()) <= 250
    long = []
    for path in CORE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > 85:
                    long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, long


def test_stage_vocabulary_is_one():
    """The stage table, the timings and the settings' sections say the same names in the same order."""
    import numpy as np

    from mtcw_core.chain import STAGE_NAMES, process_frame

    from mtcw_core.simulate import simulate_frame

    from .conftest import make_scene, tones

    assert STAGE_NAMES == ("validate", "gate", "spectrum", "doppler", "extract", "mix", "resolve", "select", "square")
    sections = [line.strip()[5:] for line in (CORE / "profiles.py").read_text().splitlines()
                if line.strip().startswith("# -- ")]
    assert [s.split()[0] for s in sections] == list(STAGE_NAMES)
    fr = simulate_frame(make_scene(modulator=tones(500e6, 700e6, 950e6)), seed=1)
    res = process_frame(fr, "balanced")
    assert res.status == "ok"
    assert list(res.stage_seconds) == [s for s in STAGE_NAMES if s not in ("gate", "square")]  # a CW frame has no gate; a target, no square
    assert all(np.isfinite(v) and v >= 0 for v in res.stage_seconds.values())


def test_the_api_starts_without_the_chain():
    """The API only stores and serves points: importing it must not import the chain (numpy's
    DSP, scipy), which cost a restarted API ~2 s of its recovery time under load."""
    import subprocess
    import sys

    code = "import sys, services.api; print(sorted(m for m in ('mtcw_core.chain', 'scipy') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr
