"""The suite's independence: no file of tests/conformance imports the project's packages, so a
change to ``protocol/`` (or the device, or the ground) can never move both sides of a test; and
docs/conformance.md, the list of the ICD's statements, names only tests that exist."""

import ast
from pathlib import Path

import pytest

from .count_statements import REPO, statements

pytestmark = pytest.mark.timeout(30)

HERE = Path(__file__).resolve().parent
FORBIDDEN = {"protocol", "firmware_model", "ground"}


def _imports(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) in {
            "import_module",
            "__import__",
        }:
            names.update(
                a.value.split(".")[0] for a in node.args if isinstance(a, ast.Constant) and isinstance(a.value, str)
            )
    return names


def test_conf_suite_imports_nothing_of_the_project():
    """No ``import``/``from`` (nor ``importlib.import_module``/``__import__``) of protocol,
    firmware_model or ground in any file of the suite."""
    files = sorted(HERE.glob("*.py"))
    assert len(files) >= 8
    bad = {p.name: sorted(_imports(p) & FORBIDDEN) for p in files if _imports(p) & FORBIDDEN}
    assert bad == {}


def test_conf_statement_list_names_existing_tests(capsys):
    """Every test docs/conformance.md names is a test of the suite, and every conformance test is
    named there (the count the figure quotes is then the suite's)."""
    tests = set()
    for path in HERE.glob("test_conf_*.py"):
        tree = ast.parse(path.read_text())
        tests |= {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and n.name.startswith("test_conf_")}
    rows = statements(REPO / "docs" / "conformance.md")
    named = {t for r in rows for t in r["tests"]}
    assert named - tests == set(), "docs/conformance.md names tests that do not exist"
    self_tests = {"test_conf_suite_imports_nothing_of_the_project", "test_conf_statement_list_names_existing_tests"}
    assert tests - named - self_tests == set(), "tests missing from docs/conformance.md"
    icd = [r for r in rows if r["kind"] == "S"]
    checked = sum(1 for r in icd if r["tests"])
    with capsys.disabled():
        print(f"\nICD statements: {len(icd)}; checked: {checked}; not checkable: {len(icd) - checked}")
