"""The house rules that a reader relies on, checked from the source (AST, no imports run):

- imports point one way: service -> drivers, fakes, calibration; drivers and fakes ->
  calibration; calibration -> nothing of ours; drivers and fakes never import each other;
- inside service/, the layers point down: nothing below the routes, verbs and page imports them,
  and the bottom (store, rows, device configuration, settings, refusals, files) imports nothing
  above it;
- every exception class Recal defines joins one tree rooted in ``calibration.errors.RecalError``
  (in every install: a module needing an extra that is not installed is read from its source).
"""

from __future__ import annotations

import ast
import builtins
import importlib
import inspect
import pkgutil
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("calibration", "drivers", "fakes", "service")
# What each package may import of ours (itself always).
ALLOWED = {
    "calibration": set(),
    "drivers": {"calibration"},
    "fakes": {"calibration"},
    "service": {"calibration", "drivers", "fakes"},
}


def _modules(package: str):
    for path in sorted((REPO / package).rglob("*.py")):
        yield path, ast.parse(path.read_text(encoding="utf-8"), filename=str(path))


def _imported(tree: ast.AST, path: Path) -> set[str]:
    """Top-level package names of ours that the module imports (anywhere in it)."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: stays inside its own package
                continue
            names = [node.module or ""]
        else:
            continue
        out |= {n.split(".")[0] for n in names if n.split(".")[0] in PACKAGES}
    return out


@pytest.mark.parametrize("package", PACKAGES)
def test_imports_point_one_way(package):
    wrong = []
    for path, tree in _modules(package):
        for other in sorted(_imported(tree, path) - ALLOWED[package] - {package}):
            wrong.append(f"{path.relative_to(REPO)} imports {other}")
    assert not wrong, "imports that run the wrong way:\n" + "\n".join(wrong)


def _our_modules():
    """Each module of ours, imported, or (when an optional extra it needs is not installed here,
    the fleet's Procrastinate) its name and path, to be read from the source instead."""
    for package in PACKAGES:
        pkg = importlib.import_module(package)
        yield pkg
        for info in pkgutil.walk_packages(pkg.__path__, prefix=f"{package}.", onerror=lambda name: None):
            if info.name.endswith("__main__"):
                continue
            try:
                yield importlib.import_module(info.name)
            except ImportError:  # an optional extra missing in this install
                yield info.name


def _unimported_exceptions(name: str, tree_names: set[str]) -> list[str]:
    """The exception classes of a module that could not be imported here, read from its source,
    that do not derive (by name) from a class of the tree: a class whose bases include a
    built-in exception or another exception class of the module, and none of ``tree_names``."""
    path = REPO / (name.replace(".", "/") + ".py")
    if not path.exists():
        path = REPO / name.replace(".", "/") / "__init__.py"
    tree = ast.parse(path.read_text(encoding="utf-8"))
    builtin_exc = {n for n, v in vars(builtins).items() if isinstance(v, type) and issubclass(v, BaseException)}
    classes = {n.name: n for n in ast.walk(tree) if isinstance(n, ast.ClassDef)}

    def base_names(node):
        return [b.attr if isinstance(b, ast.Attribute) else getattr(b, "id", "") for b in node.bases]

    joined, outside = set(tree_names), []
    changed = True
    while changed:  # a class of the module that derives from one that joined joins too
        changed = False
        for cname, node in classes.items():
            if cname not in joined and any(b in joined for b in base_names(node)):
                joined.add(cname)
                changed = True
    for cname, node in classes.items():
        bases = base_names(node)
        is_exception = any(b in builtin_exc or b in classes for b in bases)
        if is_exception and cname not in joined:
            outside.append(f"{name}.{cname}")
    return outside


def test_every_exception_joins_the_tree():
    """Runs in every install: a module that needs an extra not installed here (the fleet's) is
    read from its source, by the names of its classes' bases."""
    from calibration.errors import RecalError

    outside, unimported, tree_names = [], [], set()
    for module in _our_modules():
        if isinstance(module, str):
            unimported.append(module)
            continue
        for name, cls in inspect.getmembers(module, inspect.isclass):
            if cls.__module__ != module.__name__ or not issubclass(cls, BaseException):
                continue
            if issubclass(cls, RecalError):
                tree_names.add(name)
            else:
                outside.append(f"{module.__name__}.{name}")
    for name in unimported:
        outside += _unimported_exceptions(name, tree_names)
    assert not outside, "exception classes outside RecalError: " + ", ".join(outside)


def test_an_exception_outside_the_tree_is_found_in_a_module_that_cannot_be_imported(tmp_path, monkeypatch):
    """The source reading itself: a module (not importable here) with one class in the tree, one
    deriving from it, and one plain ValueError that is outside."""
    pkg = tmp_path / "service" / "fleetlike.py"
    pkg.parent.mkdir(parents=True)
    pkg.write_text(
        "import procrastinate_not_installed\n"
        "from calibration.errors import RecalError\n"
        "class LeaseLost(RecalError, RuntimeError): pass\n"
        "class LeaseLostTwice(LeaseLost): pass\n"
        "class Stray(ValueError): pass\n"
        "class NotAnError: pass\n"
    )
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    assert _unimported_exceptions("service.fleetlike", {"RecalError"}) == ["service.fleetlike.Stray"]


# Inside service/: the page, the API's routes and the CLI's verbs sit on top; the use cases in
# the middle; the store, its rows, the typed device configuration, the settings, the refusals
# and the interchange files at the bottom (docs/architecture.md). Nothing below the top imports
# the top, and the bottom imports nothing above it.
SERVICE_TOP = ("service.api", "service.commands", "service.cli", "service.web")
SERVICE_BOTTOM = (
    "service.store",
    "service.models",
    "service.records",
    "service.device_config",
    "service.device_fields",  # the device configuration's field types
    "service.device_registry",  # the device registry: the configuration's model and its table
    "service.settings",
    "service.problems",
    "service.files",
    "service.textcheck",
)


def _service_modules() -> dict[str, Path]:
    out = {}
    for path in sorted((REPO / "service").rglob("*.py")):
        parts = list(path.relative_to(REPO).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _service_imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The service modules ``name`` imports (relative imports resolved; ``from x import y`` counts
    ``x.y`` when that is a module)."""
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            found = [target] + [f"{target}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            found = [a.name for a in node.names]
        else:
            continue
        out |= {f for f in found if f in modules}
    return out


def _in(name: str, layer: tuple[str, ...]) -> bool:
    """Whether module ``name`` is one of ``layer``'s modules or inside one of its packages (a
    module boundary: service.stored_compensation is not service.store)."""
    return any(name == m or name.startswith(m + ".") for m in layer)


def test_service_layers_point_down():
    modules = _service_modules()
    assert {m for m in modules if _in(m, SERVICE_BOTTOM)} and {m for m in modules if _in(m, SERVICE_TOP)}
    wrong = []
    for name, path in modules.items():
        for other in sorted(_service_imports(name, path, modules)):
            if not _in(name, SERVICE_TOP) and _in(other, SERVICE_TOP):
                wrong.append(f"{name} (below the top) imports {other}")
            if _in(name, SERVICE_BOTTOM) and not _in(other, SERVICE_BOTTOM):
                wrong.append(f"{name} (the bottom) imports {other}")
    assert not wrong, "imports that run up service/'s layers:\n" + "\n".join(wrong)


def test_only_the_device_registry_names_a_concrete_driver():
    """A robot's or an instrument's driver module (``drivers.ur_rtde``, ``drivers.ippdme``, ...)
    is imported in service/ by the registry alone (issue 23): the rest reaches devices through
    its table and the interfaces of ``drivers.base`` (and ``drivers.errors``)."""
    shared = {"base", "errors"}
    concrete = {f"drivers.{p.stem}" for p in (REPO / "drivers").glob("*.py") if p.stem not in shared}
    concrete.discard("drivers.__init__")
    wrong = []
    for name, path in _service_modules().items():
        if name == "service.device_registry":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and not node.level:
                found = {node.module or ""}
            elif isinstance(node, ast.Import):
                found = {a.name for a in node.names}
            else:
                continue
            wrong += [f"{name} imports {m}" for m in sorted(found & concrete)]
    assert not wrong, "drivers named outside service/device_registry.py:\n" + "\n".join(wrong)


def test_routes_are_http_only():
    """A route parses the request, calls a use case and answers: no numpy (math belongs in
    calibration/), no drivers (devices are opened by the use cases), no other route (what two
    routes share is a use case of service/)."""
    wrong = []
    for path in sorted((REPO / "service" / "api" / "routes").glob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level == 1:  # `from .x import`: another route
                    wrong.append(f"{path.name} imports the route module .{node.module}")
                    continue
                names = [node.module or ""]
            else:
                continue
            for n in names:
                if n.split(".")[0] in ("numpy", "drivers"):
                    wrong.append(f"{path.name} imports {n}")
    assert not wrong, "routes that do more than HTTP:\n" + "\n".join(wrong)
