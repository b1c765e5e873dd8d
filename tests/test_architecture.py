"""The house rules that a reader relies on, checked from the source (AST, no imports run):

- imports point one way: service -> drivers, fakes, calibration; drivers and fakes ->
  calibration; calibration -> nothing of ours; drivers and fakes never import each other;
- every exception class Recal defines joins one tree rooted in ``calibration.errors.RecalError``.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
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
    for package in PACKAGES:
        pkg = importlib.import_module(package)
        yield pkg
        for info in pkgutil.walk_packages(pkg.__path__, prefix=f"{package}."):
            if info.name.endswith("__main__"):
                continue
            try:
                yield importlib.import_module(info.name)
            except ImportError as exc:  # an optional client library missing here
                pytest.skip(f"{info.name}: {exc}")


def test_every_exception_joins_the_tree():
    from calibration.errors import RecalError

    outside = []
    for module in _our_modules():
        for name, cls in inspect.getmembers(module, inspect.isclass):
            if cls.__module__ != module.__name__ or not issubclass(cls, BaseException):
                continue
            if not issubclass(cls, RecalError):
                outside.append(f"{module.__name__}.{name}")
    assert not outside, "exception classes outside RecalError: " + ", ".join(outside)


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
