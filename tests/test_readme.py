"""The README's tour runs as written, and what the README and docs/ name exists."""

import importlib.util
import os
import re
import stat
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def _blocks(text: str, marker: str = "") -> list[str]:
    """Fenced blocks of ``text`` (those right after a ``<!-- marker -->`` line when given)."""
    lead = rf"<!-- {marker} -->\n" if marker else ""
    return [b.strip() for b in re.findall(rf"^{lead}```[a-z]*\n(.*?)^```", text, flags=re.S | re.M)]


def _python_wrapper(tmp: Path) -> None:
    """``tmp/.venv/bin/python``: this interpreter, so the README's lines run unchanged."""
    exe = tmp / ".venv" / "bin" / "python"
    exe.parent.mkdir(parents=True)
    exe.write_text(f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')
    exe.chmod(exe.stat().st_mode | stat.S_IXUSR)


def _run(command: str, cwd: Path) -> str:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run(["bash", "-euo", "pipefail", "-c", command], cwd=cwd, env=env, capture_output=True, text=True)
    assert done.returncode == 0, f"{command}\n{done.stdout[-2000:]}\n{done.stderr[-3000:]}"
    return done.stdout


def test_readme_tour_runs_as_written(tmp_path: Path):
    """Command 1's dataset and training, made smaller (fewer scenes and steps), then every tour
    block verbatim: export, the demo plate, the composite, the evaluation report."""
    _python_wrapper(tmp_path)
    for name in ("train.py", "export.py", "configs"):
        (tmp_path / name).symlink_to(ROOT / name)
    readme = (ROOT / "README.md").read_text()
    main_job = _blocks(readme)[0].split("&&")
    synth, train = (c.strip() for c in main_job if "data_tools.synth" in c or "train.py" in c)
    assert "--scenes 8" in synth and "--slices 4" in synth and train.endswith("--overwrite")
    _run(synth.replace("--scenes 8", "--scenes 4").replace("--slices 4", "--slices 2"), tmp_path)
    _run(train.replace("--overwrite", "train.steps=3 train.eval_every=3 train.checkpoint_every=3 --overwrite"), tmp_path)
    tour = _blocks(readme, "tour")
    assert len(tour) == 3, "the tour's blocks are marked <!-- tour -->"
    for block in tour:
        _run(block, tmp_path)
    assert (tmp_path / "runs/quickstart/lens.onnx").is_file()
    assert (tmp_path / "data/demo/comp.exr").is_file()
    report = (tmp_path / "report" / "report.md").read_text()
    for row in ("gaussian", "scatter", "lens.onnx", "checkpoint.pt"):
        assert row in report, f"{row} missing from the tour's report"


def _mentions(pattern: str) -> set[tuple[str, str]]:
    return {(page.name, m) for page in PAGES for m in re.findall(pattern, page.read_text())}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_relative_links_resolve(page: Path):
    text = page.read_text()
    for target in re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", text):
        assert (page.parent / target).exists(), f"{page.name} links to {target}, which does not exist"
    for target, anchor in re.findall(r"\]\(([^)#:]*)#([^)]+)\)", text):
        linked = page if not target else page.parent / target
        anchors = {re.sub(r"[^a-z0-9 _-]", "", h.lower()).replace(" ", "-")
                   for h in re.findall(r"^#+ (.+)$", linked.read_text(), flags=re.M)}
        assert anchor in anchors, f"{page.name} links to {target}#{anchor}; headings there: {sorted(anchors)}"


def test_named_modules_scripts_and_configs_exist():
    for page, module in _mentions(r"python -m ([a-z_][a-z0-9_.]*)"):
        if module.split(".")[0] in ("neuralbokeh", "data_tools"):
            assert importlib.util.find_spec(module) is not None, f"{page} names python -m {module}"
    for page, path in _mentions(r"\b((?:benchmarks|configs|tests|neuralbokeh|data_tools)/[A-Za-z0-9_/.]+\.(?:py|toml))"):
        assert (ROOT / path).is_file(), f"{page} names {path}, which does not exist"


def test_readme_is_the_manual_and_docs_hold_the_record():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 250
    # measured tables belong in docs/benchmarks.md, each after its command
    assert not re.search(r"^\| .*\b(ms|dB|PSNR)\b.*\|$", readme, flags=re.M), "a measured table in the README"


def test_the_install_table_names_every_dependency():
    """Each row of the README's install table lists what that extra pulls in ``pyproject.toml``."""
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    groups = {"runtime": project["dependencies"], **{k: v for k, v in project["optional-dependencies"].items() if k != "runtime"}}
    rows = {m.group(1): m.group(0) for m in re.finditer(r'^\| `(?:pip install "neuralbokeh)?\[(\w+)\].*$',
                                                       (ROOT / "README.md").read_text(), flags=re.M)}
    for group, deps in groups.items():
        if group == "tensorboard":
            continue  # an optional curve viewer, named where training's logs are described
        assert group in rows, f"no README install row for [{group}]"
        for dep in deps:
            name = re.match(r"[A-Za-z0-9_.-]+", dep).group(0)
            if name == "neuralbokeh":
                continue  # another extra of this package, named in its row as "[train]" or "everything above"
            assert name.lower() in rows[group].lower(), f"README's [{group}] row does not name {name}: {rows[group]}"
