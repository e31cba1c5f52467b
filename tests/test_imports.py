"""The import graph goes one way (STYLE.md habit 1): protocol/ and recordings/ import neither zmq nor jax
nor the service or clients; clients/ never import the service or jax. Checked statically with `ast`, so a
lazy import inside a function counts too."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

FORBIDDEN = {
    "protocol": {"zmq", "jax", "jaxlib", "optimistix", "lineax", "equinox", "service", "clients", "recordings"},
    "recordings": {"zmq", "jax", "jaxlib", "optimistix", "lineax", "equinox", "service", "clients"},
    "clients": {"service", "jax", "jaxlib", "optimistix", "lineax", "equinox"},
    # Only service/ imports jax (STYLE.md); benchmarks drive the engine through service/.
    "benchmarks": {"jax", "jaxlib", "optimistix", "lineax", "equinox"},
}


def imported_top_level(path: Path) -> set[str]:
    """Top-level package names a module imports, anywhere in it (relative imports resolve to its own
    package, which is never forbidden for itself)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def test_the_checker_sees_imports(tmp_path):
    """Guard against a checker that cannot fail."""
    source = tmp_path / "m.py"
    source.write_text("import zmq.asyncio\nfrom service.engine import Engine\ndef f():\n    import jax\nfrom . import x\n")
    assert imported_top_level(source) == {"zmq", "service", "jax"}


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_layers_import_one_way(package):
    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"package {package} has no modules"
    offenders = {
        str(path.relative_to(ROOT)): sorted(imported_top_level(path) & FORBIDDEN[package]) for path in files
    }
    assert {k: v for k, v in offenders.items() if v} == {}


def test_protocol_needs_only_stdlib_numpy_msgpack():
    """Any tool can speak the protocol with two small dependencies."""
    import sys

    allowed = set(sys.stdlib_module_names) | {"numpy", "msgpack", "protocol", "__future__"}
    used = set().union(*(imported_top_level(path) for path in (ROOT / "protocol").rglob("*.py")))
    assert used - allowed == set()
