"""Benchmark scripts (bench/*.py) loaded as modules by the tests that reuse their code."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

BENCH = Path(__file__).resolve().parents[1] / "bench"


def load_bench(name: str) -> ModuleType:
    """bench/NAME.py as a module, loaded once per process."""
    key = f"pdtool_bench_{name}"
    if key not in sys.modules:
        spec = importlib.util.spec_from_file_location(key, BENCH / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[key] = mod  # before exec: dataclasses and pickling look the module up
        spec.loader.exec_module(mod)
    return sys.modules[key]
