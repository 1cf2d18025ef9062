"""The package's layout: each folder one concept, imports only downwards, no cycles.

Read from the source (every `import` and `from ... import`, those inside functions included),
so a late import inside a function cannot hide an upward dependency."""
import ast
import graphlib
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "rscasadi"

# bottom to top: a module may import its own room and the rooms below it
LAYERS = [{"spatial", "files", "interrupt", "errors"}, {"model"}, {"dynamics"}, {"native"}, {"codegen"}, {"sim", "export"}, {"task"},
          {"ocp"},
          {"mpc", "interaction"}, {"identification"}, {"studies", "view"}, {"cli", "__init__"}]
REFERENCE = "reference"        # the independent references: they may import the model, nothing imports them


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports() -> dict:
    """module -> the rscasadi modules it imports."""
    files = {module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph = {}
    for name, path in files.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        found = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[:len(package.split(".")) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                for alias in node.names:
                    full = f"{target}.{alias.name}"
                    found.add(full if full in files else target)
            elif isinstance(node, ast.Import):
                found.update(alias.name for alias in node.names)
        graph[name] = {m for m in found if m in files and m != name}
    return graph


def room(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def rank(module: str) -> int:
    return next(i for i, layer in enumerate(LAYERS) if room(module) in layer)


GRAPH = imports()


def test_every_module_has_a_room():
    for module in GRAPH:
        assert room(module) == REFERENCE or any(room(module) in layer for layer in LAYERS), module


def test_no_import_cycles():
    try:
        list(graphlib.TopologicalSorter(GRAPH).static_order())
    except graphlib.CycleError as exc:
        pytest.fail(f"import cycle: {' -> '.join(exc.args[1])}")


def test_imports_only_downwards():
    upward = [(a, b) for a, deps in GRAPH.items() for b in deps
              if room(a) != REFERENCE and room(b) != REFERENCE and rank(b) > rank(a)]
    assert not upward, "\n".join(f"{a} imports {b}" for a, b in upward)


def test_the_references_stay_independent():
    """The numpy core and the Pinocchio route check the library; the library never uses them,
    and they use nothing of it but the model they read (and its error classes)."""
    assert not [a for a, deps in GRAPH.items() for b in deps if room(b) == REFERENCE and room(a) != REFERENCE]
    assert all(room(b) in ("model", "spatial", "errors", REFERENCE) for a, deps in GRAPH.items() if room(a) == REFERENCE
               for b in deps)


def test_the_graph_is_read():
    """The reader finds the imports it must (else the tests above would pass on an empty graph)."""
    assert "rscasadi.model.modelfile" in GRAPH["rscasadi.dynamics.arm"]
    assert "rscasadi.native.build" in GRAPH["rscasadi.codegen.generate"]
    assert len(GRAPH) > 40


def test_every_error_rscasadi_defines_is_an_rscasadi_error():
    """`except rscasadi.Error` catches every error class the package defines (found in the source,
    not listed by hand), and each keeps a builtin base for older handlers."""
    import importlib
    import inspect
    import rscasadi
    found = []
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and any(
                    getattr(b, "id", getattr(b, "attr", "")).endswith(("Error", "Exception", "Failed")) for b in node.bases):
                found.append((module_name(path), node.name))
    assert len(found) >= 9, found
    for module, name in found:
        cls = getattr(importlib.import_module(module), name)
        assert issubclass(cls, rscasadi.Error), f"{module}.{name}"
        assert cls is rscasadi.Error or issubclass(cls, (ValueError, RuntimeError, TypeError, KeyError)), \
            f"{module}.{name}"
        assert inspect.getdoc(cls), f"{module}.{name} says what it means"


def test_the_library_raises_only_its_own_errors():
    """No bare builtin exception: each raise is an rscasadi.Error (which keeps its builtin base)."""
    bare = [f"{path.relative_to(PACKAGE.parent)}:{node.lineno}" for path in PACKAGE.rglob("*.py")
            for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, ast.Raise) and isinstance(node.exc, ast.Call)
            and getattr(node.exc.func, "id", "") in ("ValueError", "RuntimeError", "TypeError", "KeyError",
                                                       "Exception", "AssertionError")]
    assert not bare, "raise rscasadi.errors' classes instead: " + ", ".join(bare)
