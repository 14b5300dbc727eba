"""The layout's rules, checked on the source (issue 7): pyopencl only under cm2cl/device, the reference
twins independent of the code they check and called by no production path, each folder says what
it owns."""

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "cm2cl"


def _imports(path: Path):
    """(module, level) of every import in a file, at any depth."""
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, 0
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level == 0:
                yield base, 0
            else:   # resolve relative imports against the file's package
                pkg = path.relative_to(PKG.parent).with_suffix("").parts[:-node.level]
                yield ".".join(pkg + ((base,) if base else ())), 0
                for a in node.names:
                    yield ".".join(pkg + ((base,) if base else ()) + (a.name,)), 0


def test_only_the_device_layer_imports_pyopencl():
    offenders = [str(p.relative_to(PKG)) for p in PKG.rglob("*.py") if "device" not in p.parts
                 and any(m.split(".")[0] == "pyopencl" for m, _ in _imports(p))]
    assert offenders == []


def test_reference_is_independent_and_unused_in_production():
    allowed = {"cm2cl.solver.control", "cm2cl.solver.params", "cm2cl.solver.result"}
    for p in (PKG / "reference").glob("*.py"):
        for m, _ in _imports(p):
            if m.startswith("cm2cl.") and not m.startswith("cm2cl.reference"):
                assert any(m == a or m.startswith(a + ".") for a in allowed) or m in (
                    "cm2cl.solver", "cm2cl"), f"{p.name} imports {m}"
            assert not m.startswith(("cm2cl.device", "cm2cl.solver.forward", "cm2cl.solver.admm")), (p.name, m)
    users = [str(p.relative_to(PKG)) for p in PKG.rglob("*.py") if "reference" not in p.parts
             and any(m.startswith("cm2cl.reference") for m, _ in _imports(p))]
    assert users == []


def test_each_folder_says_what_it_owns():
    for d in [p for p in PKG.iterdir() if p.is_dir() and not p.name.startswith("__")]:
        init = d / "__init__.py"
        if d.name == "scenes" or not any(d.glob("*.py")):
            continue
        doc = ast.get_docstring(ast.parse(init.read_text()))
        assert doc and len(doc) > 40, f"{d.name}/__init__.py has no docstring saying what it owns"


def test_every_subpackage_ships_in_the_wheel():
    """pyproject.toml lists the packages by name: a new subpackage missing there is absent from the wheel
    (and the installed package fails to import)."""
    import tomllib

    listed = set(tomllib.loads((PKG.parent / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(PKG.parent).parts) for p in PKG.rglob("__init__.py")}
    assert found <= listed, sorted(found - listed)
