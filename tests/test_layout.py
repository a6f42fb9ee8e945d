"""The architecture's rules (DESIGN.md section 1), checked on the source: no import cycle among
the modules of ``bftaichi`` and ``kernels`` (function-level imports count too), ``kernels``
never imports ``bftaichi``, and no module over 600 lines."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("bftaichi", "kernels")


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _imports(name: str, path: Path, modules: dict) -> set[str]:
    """The project modules ``name`` imports anywhere in its file (resolved to module names)."""
    is_pkg = path.name == "__init__.py"
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".") if is_pkg else name.split(".")[:-1]
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            # a submodule imported from its package (``from .. import backend``) depends on
            # the submodule; any other name on the module that defines it
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base
                       for a in node.names]
        else:
            continue
        for t in targets:
            while t and t not in modules:  # a name imported from a module: its module
                t = t.rpartition(".")[0]
            if t and t != name:
                found.add(t)
    return found


def _graph():
    modules = _modules()
    return {m: _imports(m, p, modules) for m, p in modules.items()}


def test_no_import_cycle_counting_function_level_imports():
    edges = _graph()
    state, stack, cycles = {}, [], []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for t in sorted(edges[m]):
            if state.get(t) == 1:
                cycles.append(stack[stack.index(t):] + [t])
            elif t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m)
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_kernels_never_imports_bftaichi():
    bad = {m: sorted(t for t in ts if t.split(".")[0] == "bftaichi")
           for m, ts in _graph().items() if m.split(".")[0] == "kernels"}
    assert not any(bad.values()), bad


def test_no_module_over_600_lines():
    long = {str(p.relative_to(ROOT)): n for p in _modules().values()
            if (n := len(p.read_text().splitlines())) > 600}
    assert not long, long


def test_every_tool_measures_its_own_checkout():
    """A script under ``tools/`` or ``docs/experiments/`` that imports the project puts its own
    checkout first on ``sys.path`` before it does (``import checkout``, or the root inserted
    by hand): ``python tools/X.py`` otherwise imports whichever bftaichi is installed, and a
    before/after comparison run from two checkouts measures one of them twice."""
    unguarded = []
    for path in sorted([*(ROOT / "tools").glob("*.py"), *(ROOT / "docs" / "experiments").glob("*.py")]):
        tree = ast.parse(path.read_text())
        first = None  # the line of the first import of bftaichi or kernels, anywhere in the file
        for node in ast.walk(tree):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            if any(n.split(".")[0] in PACKAGES for n in names):
                first = node.lineno if first is None else min(first, node.lineno)
        if first is None or path.name == "checkout.py":
            continue
        lines = path.read_text().splitlines()[:first - 1]
        if not any(line.startswith("import checkout") or "sys.path.insert(0, str(ROOT))" in line
                   for line in lines):
            unguarded.append(path.relative_to(ROOT).as_posix())
    assert not unguarded, f"import bftaichi before putting this checkout on sys.path: {unguarded}"


def test_a_tools_child_process_imports_the_tools_checkout_from_any_directory(tmp_path):
    """tools/checkout.py's child_env: a child ``python -m`` started in another directory that
    holds a bftaichi of its own (another checkout) still imports the tool's checkout."""
    import os
    import subprocess
    import sys

    sys.path.insert(0, str(ROOT / "tools"))
    try:
        import checkout
    finally:
        sys.path.remove(str(ROOT / "tools"))
    decoy = tmp_path / "bftaichi"
    decoy.mkdir()
    (decoy / "__init__.py").write_text("raise ImportError('the working directory was imported')\n")
    env = checkout.child_env()
    env.pop("PYTHONSAFEPATH")
    shadowed = subprocess.run([sys.executable, "-c", "import bftaichi"], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=120)
    assert shadowed.returncode != 0  # the decoy works: without the setting it is imported
    done = subprocess.run([sys.executable, "-c", "import bftaichi; print(bftaichi.__file__)"],
                          cwd=tmp_path, env=checkout.child_env(), capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    assert os.path.realpath(done.stdout.strip()) == os.path.realpath(ROOT / "bftaichi" /
                                                                      "__init__.py")
    # a tool started as a child (bench_pipeline.py runs itself for Open3D) finds checkout.py
    done = subprocess.run([sys.executable, str(ROOT / "tools" / "bench_pipeline.py"), "--help"],
                          cwd=tmp_path, env=checkout.child_env(), capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
