"""The layering of docs/architecture.md, read from the source with ``ast``: every
import in calib_cli (top-level or inside a function) goes down, never up or
sideways between siblings, and nothing in the package imports ``validation/``.

    base (errors, units, geometry, plan, data)  <-  model  <-  (sim, methods)
        <-  io  <-  (acquire, batch, report, design)  <-  cli
    validation: may import anything; imported by nothing in the package

Compatibility aliases left at the old paths of moved modules are listed in SHIMS;
they may hold nothing but imports (and the ``sys.modules`` alias line).
"""

from __future__ import annotations

import ast
import shutil
from pathlib import Path

import calib_cli

PACKAGE = Path(calib_cli.__file__).parent

# unit (top-level module or subpackage of calib_cli) -> rank; lower ranks are lower layers
RANK = {"": 0, "errors": 0, "units": 0, "geometry": 0, "plan": 0, "data": 0, "docs_path": 0,
        "model": 1,
        "sim": 2, "methods": 2,
        "io": 3,
        "acquire": 4, "batch": 4, "report": 4, "design": 4, "api": 4,
        "cli": 5, "__main__": 6,
        "validation": 7}
# units of the same rank may import each other only along these edges
SIDEWAYS_OK: set = set()  # none: the tolerance evaluator and the history are in io/ (issue 33)
BASE = {"", "errors", "units", "geometry", "plan", "data", "docs_path"}  # one layer: may import each other

# old path -> why it may import upwards: re-exports left for the branches open when the
# module moved (delete each once those branches are merged)
SHIMS: dict = {}  # none left: the branches open when modules moved are merged


def _unit(parts: list[str]) -> str:
    """calib_cli.<unit>...: the layer unit of a dotted module path below calib_cli."""
    return parts[0] if parts else ""


def _imports(path: Path, package_root: Path):
    """(line, target module parts below calib_cli) of every calib_cli import in a file."""
    rel = path.relative_to(package_root).with_suffix("")
    mod = list(rel.parts)
    is_pkg = mod[-1] == "__init__"
    if is_pkg:
        mod = mod[:-1]
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                p = a.name.split(".")
                if p[0] == "calib_cli":
                    yield node.lineno, p[1:]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = mod if is_pkg else mod[:-1]
                base = base[:len(base) - (node.level - 1)]
                target = base + (node.module.split(".") if node.module else [])
            else:
                p = (node.module or "").split(".")
                if p[0] != "calib_cli":
                    continue
                target = p[1:]
            if target:
                yield node.lineno, target
            else:  # from calib_cli import x: x is a unit (or a name of calib_cli/__init__)
                for a in node.names:
                    yield node.lineno, [a.name] if a.name in RANK else []


def layer_violations(package_root: Path = PACKAGE) -> list[str]:
    """One line per import that breaks the layering: file:line, who imports what, why."""
    out = []
    for path in sorted(package_root.rglob("*.py")):
        rel = path.relative_to(package_root)
        parts = list(rel.with_suffix("").parts)
        src = _unit(parts if parts[-1] != "__init__" else parts[:-1])
        if rel.as_posix() in SHIMS:
            continue
        if src not in RANK:
            out.append(f"calib_cli/{rel.as_posix()}:1: {src!r} is in no layer "
                       "(add it to RANK in tests/test_layers.py and docs/architecture.md)")
            continue
        for line, target in _imports(path, package_root):
            dst = _unit(target)
            if dst == src or dst not in RANK:
                continue
            where = f"calib_cli/{rel.as_posix()}:{line}"
            what = "calib_cli." + ".".join(target)
            if dst == "validation" and src != "validation":
                out.append(f"{where}: {src} imports {what}: nothing in the package imports "
                           "validation/")
            elif RANK[dst] > RANK[src]:
                out.append(f"{where}: {src or 'calib_cli'} imports {what}: upward "
                           f"({src or 'base'} is below {dst})")
            elif (RANK[dst] == RANK[src] and (src, dst) not in SIDEWAYS_OK
                  and not (src in BASE and dst in BASE) and src != "validation"):
                out.append(f"{where}: {src} imports {what}: sideways ({src} and {dst} are "
                           "siblings and do not import each other)")
    return out


def test_imports_go_down():
    bad = layer_violations()
    assert not bad, "imports against the layering (docs/architecture.md):\n" + "\n".join(bad)


def test_shims_hold_only_imports():
    """A compatibility alias must not grow code: docstring, imports, the alias line."""
    for rel in SHIMS:
        path = PACKAGE / rel
        assert path.is_file(), f"calib_cli/{rel} is listed in SHIMS but missing"
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            ok = isinstance(node, (ast.Import, ast.ImportFrom)) or (
                isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)) or (
                isinstance(node, ast.Assign) and ast.unparse(node) == "sys.modules[__name__] = _moved")
            assert ok, f"calib_cli/{rel}:{node.lineno}: a compatibility alias holds only imports"


def test_planted_upward_import_is_caught(tmp_path):
    """The checker fails on an upward import planted into a copy of the package,
    naming the file and the line; also on a lazy import inside a function and on
    an import of validation/ from the package."""
    root = tmp_path / "calib_cli"
    shutil.copytree(PACKAGE, root, ignore=shutil.ignore_patterns("__pycache__"))
    (root / "model" / "planted.py").write_text(
        '"""planted"""\nimport numpy as np\n\nfrom calib_cli.cli.render import display_of\n')
    (root / "methods" / "planted.py").write_text(
        "def f():\n    from ..sim import simulate\n    return simulate\n")
    (root / "io" / "planted.py").write_text("from calib_cli.validation import archive\n")
    (root / "data_planted.py").write_text("x = 1\n")
    bad = layer_violations(root)
    assert any(b.startswith("calib_cli/model/planted.py:4: model imports calib_cli.cli.render: "
                            "upward") for b in bad), bad
    assert any(b.startswith("calib_cli/methods/planted.py:2: methods imports calib_cli.sim: "
                            "sideways") for b in bad), bad
    assert any(b.startswith("calib_cli/io/planted.py:1:") and "validation" in b for b in bad), bad
    assert any(b.startswith("calib_cli/data_planted.py:1:") and "no layer" in b for b in bad), bad
    assert len(bad) == 4, bad
