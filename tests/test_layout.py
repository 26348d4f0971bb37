"""The layout rules of ARCHITECTURE.md that code can check: model/ is pure physics and numerics and
reads no YAML (the caller parses config files and passes dicts: issue 8)."""
from __future__ import annotations

import ast
from pathlib import Path

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
