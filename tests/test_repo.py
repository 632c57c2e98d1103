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


def test_library_never_imports_the_tools_and_never_prints():
    """Library code logs; only ``neuralbokeh/cli.py`` (the error line every CLI ends with) prints."""
    for path in (ROOT / "neuralbokeh").rglob("*.py"):
        assert not any(n.startswith("data_tools") for n in _imports(path)), path
        if path.name == "cli.py" and path.parent.name == "neuralbokeh":
            continue
        calls = [n for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.Call)]
        assert not any(isinstance(c.func, ast.Name) and c.func.id == "print" for c in calls), f"print() in {path}"


def test_pure_math_modules_import_no_torch_and_nothing_else_of_the_package():
    for name in ("optics", "apertures", "checks"):
        package_imports = {n for n in _imports(ROOT / "neuralbokeh" / f"{name}.py") if n.startswith(".")}
        assert package_imports <= {".checks"}, (name, package_imports)
    code = (
        "import sys, neuralbokeh, neuralbokeh.optics, neuralbokeh.apertures, neuralbokeh.checks; "
        "assert 'torch' not in sys.modules, 'torch was imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_model_is_pure_definitions():
    # the networks know nothing of files, datasets or training (DESIGN.md)
    for name in ("model", "lensnet", "tiling"):
        imports = _imports(ROOT / "neuralbokeh" / f"{name}.py")
        assert not any(n.lstrip(".").split(".")[0] in ("io", "data", "training", "OpenImageIO") for n in imports), (name, imports)


def test_compositing_path_never_imports_torch():
    # DESIGN.md: compositing machines have no torch
    for name in ("runtime", "composite", "masks", "normalization", "optics", "checks", "io"):
        imports = _imports(ROOT / "neuralbokeh" / f"{name}.py")
        assert not any(n.split(".")[0] in ("torch", "kornia") for n in imports), (name, imports)
    code = ("import sys, neuralbokeh.runtime, neuralbokeh.composite, neuralbokeh.masks; "
            "assert 'torch' not in sys.modules, 'torch was imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)
