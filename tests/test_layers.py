"""The import direction of the layers (docs/ARCHITECTURE.md): ``protocol`` imports neither of the
others, ``firmware_model`` never imports ``ground``; checked on every module's source, lazy
imports inside functions included."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {"protocol": ("firmware_model", "ground"), "firmware_model": ("ground",)}


def _imported(path: Path) -> set[str]:
    """Top-level package names imported anywhere in the module (absolute imports)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("layer", sorted(FORBIDDEN))
def test_a_layer_never_imports_the_ones_above_it(layer):
    modules = sorted((ROOT / layer).rglob("*.py"))
    assert modules
    offenders = {
        str(p.relative_to(ROOT)): sorted(_imported(p) & set(FORBIDDEN[layer]))
        for p in modules
        if _imported(p) & set(FORBIDDEN[layer])
    }
    assert not offenders, offenders


def test_the_check_sees_an_import_inside_a_function(tmp_path):
    src = tmp_path / "m.py"
    src.write_text("def f():\n    from ground.client import Client\n    import firmware_model.device\n")
    assert _imported(src) == {"ground", "firmware_model"}
