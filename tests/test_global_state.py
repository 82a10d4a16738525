"""No script or module changes process-wide state it does not own (STYLE.md, habit 19), read from every file's syntax.

* No ``sys.path`` edits anywhere (library, scripts, tests): a script imports the installed package, and a helper that
  scripts and tests share lives in the package (:mod:`torch_appearance.testing`), not in ``tests/``. A script may
  import a module beside it: Python puts the script's folder on the path itself.
* No ``matplotlib.use`` in the library: the backend belongs to the program; library figures are
  :class:`matplotlib.figure.Figure` objects saved by :func:`torch_appearance.io.save_figure`. A script's ``main``
  may choose its backend.

Both scans are checked against a file that breaks each rule, so they can fail.
"""
import ast
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGE = os.path.join(ROOT, "torch_appearance")


def _python_files(*folders):
    for top in folders:
        for folder, dirs, files in os.walk(os.path.join(ROOT, top)):
            dirs[:] = [d for d in dirs if not d.startswith(".") and d != "__pycache__"]
            yield from (os.path.join(folder, name) for name in sorted(files) if name.endswith(".py"))


def _dotted(node):
    """``a.b.c`` of an attribute chain of names, else None."""
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    return ".".join([node.id] + parts[::-1]) if isinstance(node, ast.Name) else None


def _aliases(tree, module):
    """The names under which ``module`` (``sys``, ``matplotlib``) is imported in ``tree``, and the names bound to
    its attributes by ``from module import x``: ({alias of module}, {local name: attribute})."""
    names, members = set(), {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.asname or a.name for a in node.names if a.name == module)
        elif isinstance(node, ast.ImportFrom) and node.module == module and not node.level:
            members.update({a.asname or a.name: a.name for a in node.names})
    return names, members


def sys_path_edits(source):
    """Line numbers of ``sys.path`` changes in ``source``: assignments to it or its items, its mutating methods,
    ``site.addsitedir``."""
    tree = ast.parse(source)
    sys_names, sys_members = _aliases(tree, "sys")
    paths = {f"{n}.path" for n in sys_names} | {local for local, attr in sys_members.items() if attr == "path"}
    site_names, site_members = _aliases(tree, "site")
    adders = {f"{n}.addsitedir" for n in site_names} | {k for k, v in site_members.items() if v == "addsitedir"}
    lines = []
    for node in ast.walk(tree):
        targets = []
        if isinstance(node, (ast.Assign, ast.AugAssign, ast.AnnAssign, ast.Delete)):
            targets = node.targets if isinstance(node, (ast.Assign, ast.Delete)) else [node.target]
        for target in targets:
            base = target.value if isinstance(target, ast.Subscript) else target
            if _dotted(base) in paths:
                lines.append(node.lineno)
        if isinstance(node, ast.Call):
            name = _dotted(node.func)
            if name in adders or (isinstance(node.func, ast.Attribute) and _dotted(node.func.value) in paths
                                  and node.func.attr in ("insert", "append", "extend", "remove", "pop", "clear")):
                lines.append(node.lineno)
    return sorted(lines)


def matplotlib_use_calls(source):
    """Line numbers of ``matplotlib.use(...)`` calls in ``source`` (under any alias)."""
    tree = ast.parse(source)
    names, members = _aliases(tree, "matplotlib")
    calls = {f"{n}.use" for n in names} | {local for local, attr in members.items() if attr == "use"}
    return sorted(node.lineno for node in ast.walk(tree)
                  if isinstance(node, ast.Call) and _dotted(node.func) in calls)


def _offenders(check, files):
    found = []
    for path in files:
        with open(path, encoding="utf-8") as handle:
            found += [f"{os.path.relpath(path, ROOT)}:{line}" for line in check(handle.read())]
    return found


def test_no_file_edits_sys_path():
    found = _offenders(sys_path_edits, _python_files("torch_appearance", "scripts", "tests"))
    assert not found, "sys.path edited at:\n" + "\n".join(found)


def test_no_library_module_chooses_the_matplotlib_backend():
    found = _offenders(matplotlib_use_calls, _python_files("torch_appearance"))
    assert not found, "matplotlib.use in the library at:\n" + "\n".join(found)


@pytest.mark.parametrize("source, lines", [
    ("import sys\nsys.path.insert(0, 'x')\n", [2]),
    ("import os, sys as s\n\ns.path.append(os.getcwd())\n", [3]),
    ("from sys import path\npath[:0] = ['x']\n", [2]),
    ("import sys\nsys.path = ['x'] + sys.path\n", [2]),
    ("import site\nsite.addsitedir('x')\n", [2]),
    ("import sys\nprint(sys.path)\nfrom os import path\npath.join('a')\n", []),
])
def test_the_scan_sees_a_sys_path_edit(source, lines):
    assert sys_path_edits(source) == lines


@pytest.mark.parametrize("source, lines", [
    ("def f():\n    import matplotlib\n    matplotlib.use('Agg')\n", [3]),
    ("import matplotlib as mpl\nmpl.use('Agg')\n", [2]),
    ("from matplotlib import use\nuse('pdf')\n", [2]),
    ("import matplotlib.pyplot as plt\nplt.plot([1])\n", []),
])
def test_the_scan_sees_a_matplotlib_use(source, lines):
    assert matplotlib_use_calls(source) == lines


def test_the_reference_tracer_stays_independent_of_what_it_checks():
    """The numpy reference lives in the package for tests and benchmarks alike, but imports nothing of it."""
    path = os.path.join(PACKAGE, "testing", "reference_tracer.py")
    tree = ast.parse(open(path, encoding="utf-8").read())
    imported = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    imported |= {"." * n.level + (n.module or "") for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert imported <= {"__future__", "math", "time", "typing", "numpy"}, imported


@pytest.mark.parametrize("script", ["scripts/bench/bench_peer.py", "scripts/bench/bench_chromatic_curve.py"])
def test_bench_scripts_run_from_the_repository_root(script):
    """``python scripts/bench/x.py --help`` with nothing but the installed package (the reference tracer is imported
    from it, a sibling bench module from the script's own folder)."""
    result = subprocess.run([sys.executable, script, "--help"], cwd=ROOT, capture_output=True, text=True,
                            env=dict(os.environ, PYTHONPATH=""), timeout=300)
    assert result.returncode == 0, result.stderr
    assert "usage:" in result.stdout
