"""A script of benchmarks/ loaded as a module, for its tests (benchmarks/ is a folder of scripts, not a package)."""

from __future__ import annotations

import importlib.util
import sys
from types import ModuleType

from supervisor.paths import REPO_ROOT


def load_benchmark(name: str) -> ModuleType:
    """benchmarks/<name>.py, executed afresh and registered as `name` (its dataclasses resolve their annotations
    through sys.modules, and the scripts import one another by that name)."""
    spec = importlib.util.spec_from_file_location(name, REPO_ROOT / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod
