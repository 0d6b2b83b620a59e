"""The import direction of the layers (docs/ARCHITECTURE.md), checked on every module's source,
lazy imports inside functions included.

Between the top-level packages: ``protocol`` imports neither of the others, ``firmware_model``
never imports ``ground``. Inside each, the sub-packages form a stack, listed bottom first in
:data:`STACKS`: a module may import its own group and the groups below it, never one above.
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {"protocol": ("firmware_model", "ground"), "firmware_model": ("ground",)}

#: Bottom first. A group is a module path prefix; the longest matching prefix names a module's group.
STACKS = {
    "firmware_model": [
        ("firmware_model.reference_frames", "firmware_model.catalog", "firmware_model.user_files"),
        # the camera model (pixels <-> directions): identification needs it, and nothing of the pipeline
        ("firmware_model.camera",),
        ("firmware_model.ident",),
        ("firmware_model.pipeline",),
        ("firmware_model.device",),
    ],
    "ground": [
        ("ground.atomic_write", "ground.json_text", "ground.optional", "ground.arg_types", "ground.kernels"),
        ("ground.link", "ground.catalog", "ground.export"),
        ("ground.sim",),
        ("ground.calibration",),
        # the one solver face: in-process (the route chosen once) and on a device
        ("ground.solver", "ground.link_solver"),
        ("ground.analysis", "ground.testing", "ground.hil"),
        ("ground.api",),
        ("ground.cli",),
    ],
}


def _module_name(path: Path) -> str:
    return ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")


def _imports(path: Path) -> set[str]:
    """Every absolute module path the module imports (``from a.b import c`` gives ``a.b.c`` and
    ``a.b``, since ``c`` may be a module or a name in ``a.b``)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def _imported(path: Path) -> set[str]:
    """Top-level package names imported anywhere in the module (absolute imports)."""
    return {name.split(".")[0] for name in _imports(path)}


def _level(stack, module: str) -> int | None:
    """Index in ``stack`` of the group owning ``module`` (longest prefix), None if none does."""
    best, best_len = None, -1
    for i, group in enumerate(stack):
        for prefix in group:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best_len:
                best, best_len = i, len(prefix)
    return best


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


@pytest.mark.parametrize("package", sorted(STACKS))
def test_sub_packages_import_only_downwards(package):
    stack = STACKS[package]
    offenders = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        own = _level(stack, _module_name(path))
        if own is None:  # the package's own __init__
            continue
        up = sorted(
            name
            for name in _imports(path)
            if name.startswith(package + ".") and (lvl := _level(stack, name)) is not None and lvl > own
        )
        if up:
            offenders[str(path.relative_to(ROOT))] = up
    assert not offenders, offenders


def test_every_module_belongs_to_a_group():
    loose = [
        str(p.relative_to(ROOT))
        for package, stack in STACKS.items()
        for p in (ROOT / package).rglob("*.py")
        if p.name != "__init__.py" or p.parent != ROOT / package
        if _level(stack, _module_name(p)) is None
    ]
    assert not loose, loose


def test_the_command_line_is_imported_by_nothing_else():
    users = [
        str(p.relative_to(ROOT))
        for layer in ("protocol", "firmware_model", "ground")
        for p in (ROOT / layer).rglob("*.py")
        if not _module_name(p).startswith("ground.cli")
        and any(name == "ground.cli" or name.startswith("ground.cli.") for name in _imports(p))
    ]
    assert not users, users


#: What only ``ground.solver`` may use: the sky search's pipeline and the choice of a route. The
#: whole-sky index reaches the pipeline as the solve's ``patterns`` argument, never on a catalog.
ROUTE_NAMES = {"firmware_model.pipeline.sky_run", "choose_route", "Route", "InProcessSolver()"}


def _names(path: Path) -> set[str]:
    """Every name and attribute the module's source uses, every module it imports, and ``F()``
    for each name ``F`` it calls."""
    tree = ast.parse(path.read_text(), str(path))
    used = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    used |= {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
    called = {n.func for n in ast.walk(tree) if isinstance(n, ast.Call)}
    used |= {f"{f.id}()" for f in called if isinstance(f, ast.Name)}
    used |= {f"{f.attr}()" for f in called if isinstance(f, ast.Attribute)}
    return used | _imports(path) | {name.rsplit(".", 1)[-1] for name in _imports(path)}


def test_only_the_solver_module_chooses_a_route():
    """``solve_image``, ``solve-file``, ``solve --offline`` and ``replay --offline`` call
    ``ground.solver.in_process_solver``; none picks a route or runs the sky search itself."""
    choosers = {
        str(p.relative_to(ROOT)): sorted(_names(p) & ROUTE_NAMES)
        for p in sorted((ROOT / "ground").rglob("*.py"))
        if p != ROOT / "ground" / "solver.py" and _names(p) & ROUTE_NAMES
    }
    assert not choosers, choosers
    binders = [str(p.relative_to(ROOT)) for p in sorted((ROOT / "ground").rglob("*.py")) if _binds_patterns(p)]
    assert not binders, binders


def _binds_patterns(path: Path) -> bool:
    """Whether the module hangs a pattern index on a catalog object (``set_catalog_patterns``, or a
    write into a catalog's ``__dict__``) instead of passing it to the solve."""
    source = path.read_text()
    return "set_catalog_patterns" in _names(path) or "__dict__[" in source or "__dict__.setdefault" in source


def test_the_pattern_index_check_sees_a_catalog_written_to(tmp_path):
    src = tmp_path / "m.py"
    src.write_text("def f(cat, index):\n    cat.__dict__['_sky_patterns'] = index\n")
    assert _binds_patterns(src)
    src.write_text("def f(cat, index, frame, camera):\n    return run_pipeline(frame, camera, cat, patterns=index)\n")
    assert not _binds_patterns(src)


def test_the_check_sees_an_import_inside_a_function(tmp_path):
    src = tmp_path / "m.py"
    src.write_text("def f():\n    from ground.link.client import Client\n    import firmware_model.device.device\n")
    assert _imported(src) == {"ground", "firmware_model"}
    assert _level(STACKS["ground"], "ground.link.client") < _level(STACKS["ground"], "ground.cli.main")
    assert _level(STACKS["firmware_model"], "firmware_model.camera") < _level(
        STACKS["firmware_model"], "firmware_model.ident.verify"
    )
