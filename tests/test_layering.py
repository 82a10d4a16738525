"""The package's layering, enforced by reading every module's imports (lazy ones inside functions too).

A module may import from its own layer or from the layers below, never from above; the README's architecture
section draws the same table. Moving a piece up or down is a design decision: change LAYERS and the README together.
"""
import ast
import os

import pytest

PACKAGE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "torch_appearance")

#: bottom to top; a unit is a subpackage or a top-level module of torch_appearance
LAYERS = [
    {"_buildinfo", "_ext", "_C", "checks", "color"},   # build guard, input checks, colour science
    {"io", "metrics", "print_error", "progress", "interrupts"},  # files, error metrics, progress bars, Ctrl-C
    {"autograd", "render"},                             # the tracer: scene pieces, entry points, autograd Function
    {"geometry", "fabrication"},                        # meshes → voxels, inks, quantisation, printer export
    {"nn", "rings"},                                    # models and losses, ring detection
    {"distributed"},                                    # data-parallel rendering over torch.distributed
    {"pipelines"},                                      # the optimisation loops as library functions
    {"cli", "testing"},                                 # the ta-… commands, helpers for tests
]
LAYER = {unit: k for k, units in enumerate(LAYERS) for unit in units}


def _modules():
    for folder, _, files in os.walk(PACKAGE):
        for name in files:
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                rel = os.path.relpath(path, os.path.dirname(PACKAGE))[:-3].replace(os.sep, ".")
                yield path, rel[: -len(".__init__")] if rel.endswith(".__init__") else rel, name == "__init__.py"


def _unit(module):
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "torch_appearance" else None


def _imports(path, module, is_package):
    """(line, imported torch_appearance module) for every import statement of the file."""
    package = module if is_package else module.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(open(path, encoding="utf-8").read())):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                if node.module:
                    yield node.lineno, ".".join(base + [node.module])
                else:
                    for alias in node.names:
                        yield node.lineno, ".".join(base + [alias.name])
            elif node.module:
                yield node.lineno, node.module


def test_every_unit_has_a_layer():
    units = {_unit(m) for _, m, _ in _modules()} - {None}
    assert units <= set(LAYER), f"place these in LAYERS: {sorted(units - set(LAYER))}"


def test_no_module_imports_from_a_layer_above():
    upward = []
    for path, module, is_package in _modules():
        unit = _unit(module)
        if unit is None:
            continue  # torch_appearance/__init__.py, the front door, may import anything
        for line, target in _imports(path, module, is_package):
            other = _unit(target)
            if other is not None and other != unit and LAYER.get(other, -1) > LAYER[unit]:
                upward.append(f"{os.path.relpath(path, PACKAGE)}:{line} ({unit}, layer {LAYER[unit]}) imports "
                              f"{target} ({other}, layer {LAYER[other]})")
    assert not upward, "imports from a layer above:\n" + "\n".join(upward)


def test_the_check_sees_an_upward_import(tmp_path, monkeypatch):
    """The test can fail: a render module that imported the print pipeline would be reported."""
    fake = tmp_path / "torch_appearance" / "render"
    fake.mkdir(parents=True)
    (fake / "bad.py").write_text("from ..pipelines import print as p\n")
    monkeypatch.setattr(__import__(__name__), "PACKAGE", str(tmp_path / "torch_appearance"))
    with pytest.raises(AssertionError, match=r"render/bad.py:1 \(render, layer 2\) imports torch_appearance.pipelines"):
        test_no_module_imports_from_a_layer_above()
