"""Load a script of benchmarks/ as a module, for the tests of its pure functions (the benchmarks
themselves are run by hand)."""

import importlib.util
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def load(name: str):
    """benchmarks/<name>.py as the module ``name`` (registered in sys.modules: dataclasses look
    their module up)."""
    if str(BENCHMARKS) not in sys.path:  # the scripts import their helpers (_bench) as a script would
        sys.path.insert(0, str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
