"""The promises of the repository itself: README commands, CI, and the walls between parts."""

import ast
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _readme_commands() -> list[str]:
    blocks = re.findall(r"^```[a-z]*\n(.*?)^```", (ROOT / "README.md").read_text(), flags=re.S | re.M)
    return [b.strip() for b in blocks[:2]]


def test_readme_opens_with_two_commands_and_ci_runs_the_test_one():
    text = (ROOT / "README.md").read_text()
    first_fence = text.index("```")
    assert text[:first_fence].count("\n") < 6  # the commands come first
    main_job, tests = _readme_commands()
    assert "pip install -e" in main_job and "data_tools.synth" in main_job and "train.py configs/quickstart.toml" in main_job
    assert "pip install -e" in tests and "pytest" in tests
    assert tests in (ROOT / ".ci" / "run").read_text()


def _imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            names.add(("." * node.level) + (node.module or ""))
    return names


# The package's folders, each with the folders it may import (besides itself). Arrows point one
# way: lower layers never import higher ones, and the torch-free wing (core, runtime) imports
# nothing that needs torch. A new folder must be placed here.
LAYERS = {
    "core": set(),  # torch-free foundations: checks, optics, apertures, normalisation, I/O, CLI helpers
    "runtime": {"core"},  # torch-free: onnxruntime; compositing machines have no torch
    "ops": {"core"},  # torch image ops shared by networks and renderers
    "networks": {"core", "ops"},  # pure definitions
    "render": {"core", "ops"},  # classical renderers
    "data": {"core"},  # the dataset on disk
    "checkpoint": {"core", "networks"},
    "export": {"core", "runtime", "ops", "networks", "checkpoint"},
    "training": {"core", "ops", "networks", "render", "data", "checkpoint"},
    "evaluation": {"core", "runtime", "ops", "networks", "render", "data", "checkpoint", "training"},
}
TORCH_FREE = ("core", "runtime")


def _internal_imports(path: Path) -> set[str]:
    """The package folders (or top-level modules) a file of the package imports."""
    rel = path.relative_to(ROOT / "neuralbokeh").with_suffix("")
    package = ["neuralbokeh", *rel.parts[:-1]] if rel.name != "__init__" else ["neuralbokeh", *rel.parts[:-1]]
    out = set()
    for name in _imports(path):
        if name.startswith("."):
            level = len(name) - len(name.lstrip("."))
            base = package[: len(package) - level + 1] if level > 1 else package
            full = base + [p for p in name.lstrip(".").split(".") if p]
        else:
            full = name.split(".")
        if full[0] == "neuralbokeh" and len(full) > 1:
            out.add(full[1])
    return out


def _folder(path: Path) -> str:
    rel = path.relative_to(ROOT / "neuralbokeh")
    return rel.parts[0] if len(rel.parts) > 1 else rel.stem


def test_every_folder_imports_only_the_layers_below_it():
    for path in sorted((ROOT / "neuralbokeh").rglob("*.py")):
        folder = _folder(path)
        if folder == "__init__":
            assert not _internal_imports(path), path
            continue
        assert folder in LAYERS, f"{path}: place the folder {folder!r} in LAYERS"
        wrong = _internal_imports(path) - LAYERS[folder] - {folder}
        assert not wrong, f"{path.relative_to(ROOT)} ({folder}) imports {sorted(wrong)}; it may import {sorted(LAYERS[folder])}"


def test_layers_have_no_cycle():
    done: set[str] = set()
    while len(done) < len(LAYERS):
        ready = [f for f, below in LAYERS.items() if f not in done and below <= done]
        assert ready, f"cycle among {sorted(set(LAYERS) - done)}"
        done |= set(ready)


def test_torch_free_wing_never_imports_torch():
    # compositing machines have no torch: core and runtime, checked by import
    modules = sorted(".".join(("neuralbokeh",) + p.relative_to(ROOT / "neuralbokeh").with_suffix("").parts)
                     for folder in TORCH_FREE for p in (ROOT / "neuralbokeh" / folder).rglob("*.py") if p.name != "__main__.py")
    for path in (p for folder in TORCH_FREE for p in (ROOT / "neuralbokeh" / folder).rglob("*.py")):
        assert not any(n.split(".")[0] in ("torch", "kornia") for n in _imports(path)), path
    code = (f"import sys, importlib; [importlib.import_module(m) for m in {modules!r}]; "
            "assert 'torch' not in sys.modules, 'torch was imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_networks_are_pure_definitions():
    # the networks know nothing of files, datasets or training (docs/design.md)
    for path in (ROOT / "neuralbokeh" / "networks").rglob("*.py"):
        imports = _imports(path)
        assert not any(n.rsplit(".", 1)[-1] in ("io", "cli") or n.startswith("OpenImageIO") for n in imports), (path, imports)


def test_library_never_imports_the_tools_and_never_prints():
    """Library code logs; only ``neuralbokeh/core/cli.py`` (the error line every CLI ends with) prints."""
    for path in (ROOT / "neuralbokeh").rglob("*.py"):
        assert not any(n.startswith("data_tools") for n in _imports(path)), path
        if path.relative_to(ROOT).as_posix() == "neuralbokeh/core/cli.py":
            continue
        calls = [n for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.Call)]
        assert not any(isinstance(c.func, ast.Name) and c.func.id == "print" for c in calls), f"print() in {path}"


def _module_graph() -> dict[str, set[str]]:
    """Each module of ``neuralbokeh`` and ``data_tools`` -> the modules of the two it imports,
    deferred imports inside functions included."""
    paths = {}
    for top in ("neuralbokeh", "data_tools"):
        for path in (ROOT / top).rglob("*.py"):
            rel = path.relative_to(ROOT).with_suffix("")
            paths[".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)] = path
    graph = {}
    for name, path in paths.items():
        package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                deps |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = package[: len(package) - node.level + 1] if node.level else []
                full = ".".join(base + ([node.module] if node.module else []))
                deps |= {full} | {f"{full}.{a.name}" for a in node.names}
        graph[name] = {d for d in deps if d in paths and d != name}
    return graph


def test_no_module_cycle():
    """No module reaches itself through imports (a deferred import does not hide a cycle)."""
    graph, done, path = _module_graph(), set(), []

    def visit(module: str) -> None:
        path.append(module)
        for dep in sorted(graph[module]):
            assert dep not in path, "import cycle: " + " -> ".join(path[path.index(dep):] + [dep])
            if dep not in done:
                visit(dep)
        path.pop()
        done.add(module)

    for module in sorted(graph):
        if module not in done:
            visit(module)


def test_the_code_passes_the_linter():
    # ruff's settings live in pyproject.toml: pyflakes, pycodestyle, import order, 140 columns
    proc = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "."], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-1000:]
