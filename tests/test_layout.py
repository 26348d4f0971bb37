"""The layout rules of ARCHITECTURE.md that code can check: model/ is pure physics and numerics and
reads no YAML (the caller parses config files and passes dicts: issue 8)."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

MODEL = Path(__file__).resolve().parent.parent / "model"


def _imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


def test_no_module_of_model_imports_yaml_or_edge():
    files = sorted(MODEL.rglob("*.py"))
    assert len(files) > 20
    offenders = {str(p.relative_to(MODEL)): sorted(_imports(p) & {"yaml", "edge"}) for p in files}
    assert {k: v for k, v in offenders.items() if v} == {}


def test_the_daemon_imports_no_optional_extra_and_not_scipy_stats():
    """The daemon's runtime stays lean (brief: optional extras only in the commands that use them);
    scipy.stats alone is ~12 MB of RSS, and the forecast needs two of its quantiles, which
    scipy.special gives (the gateway's 250-MB target)."""
    import subprocess
    import sys
    code = ("import sys, edge.service, edge.loop, model.analysis.chain; "
            "print(sorted(m for m in ('scipy.stats', 'matplotlib', 'dask', 'distributed', 'paho', 'numba',"
            " 'llvmlite', 'threadpoolctl') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         cwd=MODEL.parent)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_the_forecast_quantiles_are_students_t_and_the_f_test():
    from scipy import special
    # tabulated values: t(0.975; 10) = 2.2281, t(0.95; 1) = 6.3138; F(1, 10) upper 5 % point 4.9646
    assert special.stdtrit(10, 0.975) == pytest.approx(2.2281, abs=1e-4)
    assert special.stdtrit(1, 0.95) == pytest.approx(6.3138, abs=1e-4)
    assert special.fdtrc(1, 10, 4.9646) == pytest.approx(0.05, abs=1e-5)
