"""Every command-line tool answers a user's mistake with one ``error:`` line naming the value and
exit status 2; ``-v`` adds the traceback."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, cwd=cwd, timeout=300)


def _one_error_line(r: subprocess.CompletedProcess, *needles: str) -> None:
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr[-2000:]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def test_train_mistakes(tmp_path, tiny_dataset):
    empty = tmp_path / "empty"
    empty.mkdir()
    out = f"train.out_dir='{tmp_path / 'out'}'"  # not the config's runs/quickstart, which may hold a run
    _one_error_line(_run("train.py", "configs/quickstart.toml", f"data.roots=['{tmp_path / 'missing'}']", out), "missing")
    _one_error_line(_run("train.py", "configs/quickstart.toml", f"data.roots=['{empty}']", out), str(empty))
    # a typo in an override is reported as the override, not against the config file
    _one_error_line(_run("train.py", "configs/quickstart.toml", "train.stpes=3", out), "override 'train.stpes=3'", "'stpes'")
    # overrides after options are taken; the missing --resume checkpoint is named
    missing = tmp_path / "nope.pt"
    r = _run("train.py", "configs/quickstart.toml", "--resume", str(missing), f"data.roots=['{tiny_dataset}']",
             f"train.out_dir='{tmp_path / 'run'}'", "train.steps=1")
    _one_error_line(r, str(missing))


def test_export_evaluate_composite_and_data_tools_mistakes(tmp_path):
    not_a_checkpoint = tmp_path / "notes.pt"
    not_a_checkpoint.write_text("hello")
    _one_error_line(_run("export.py", str(not_a_checkpoint), "--out", str(tmp_path / "m.onnx")), "not a neuralbokeh checkpoint")
    _one_error_line(_run("export.py", str(tmp_path / "missing.pt"), "--out", str(tmp_path / "m.onnx")), "missing.pt")
    _one_error_line(_run("-m", "neuralbokeh.evaluation", "--data", str(tmp_path / "nodata"), "--out", str(tmp_path / "r")), "nodata")
    _one_error_line(_run("-m", "neuralbokeh.runtime.composite", "--model", str(tmp_path / "none.onnx"), "--plate", "p.exr",
                         "--render", "r.exr", "--depth", "d.exr", "--alpha", "a.exr", "--focus", "2",
                         "--out", str(tmp_path / "c.exr")), "none.onnx")
    _one_error_line(_run("-m", "data_tools.synth", "--out", str(tmp_path / "s"), "--size", "0", "0"), "--size")
    _one_error_line(_run("-m", "data_tools.raw", str(tmp_path / "nostack"), "--out", str(tmp_path / "o")), "nostack")


def test_files_that_are_no_model_and_impossible_options_get_one_line(busy_checkpoint, busy_onnx, tiny_dataset, tmp_path):
    """Empty, truncated and foreign files given as a model or a checkpoint, an opset no onnx knows
    and a zero output size: one line naming the file or the value, no traceback."""
    empty, cut = tmp_path / "empty.onnx", tmp_path / "cut.onnx"
    empty.write_bytes(b"")
    cut.write_bytes(busy_onnx.read_bytes()[:300])
    garbage = tmp_path / "garbage.pt"
    garbage.write_text("garbage")
    plate = ("--plate", "p.exr", "--render", "r.exr", "--depth", "d.exr", "--alpha", "a.exr", "--focus", "2")
    for model in (empty, cut, busy_checkpoint):
        _one_error_line(_run("-m", "neuralbokeh.runtime.composite", "--model", str(model), *plate, "--out", str(tmp_path / "c.exr")),
                        str(model), "is not an ONNX model")
    _one_error_line(_run("-m", "neuralbokeh.evaluation", "--data", str(tiny_dataset), "--models", str(cut), "--out", str(tmp_path / "r")),
                    str(cut), "is not an ONNX model")
    _one_error_line(_run("export.py", str(garbage), "--out", str(tmp_path / "m.onnx")), str(garbage), "not a neuralbokeh checkpoint")
    _one_error_line(_run("export.py", str(busy_checkpoint), "--opset", "99", "--out", str(tmp_path / "m.onnx")), "opset", "99")
    _one_error_line(_run("-m", "data_tools.raw", str(tmp_path), "--out", str(tmp_path / "o"), "--size", "0", "0"), "--size", "0 0")
    assert not (tmp_path / "m.onnx").exists() and not (tmp_path / "c.exr").exists()


def test_evaluate_refuses_a_model_of_another_size(busy_onnx, tmp_path):
    from data_tools.synth import main as synth

    assert synth(["--out", str(tmp_path / "d"), "--scenes", "2", "--size", "24", "16", "--slices", "1", "--seed", "1"]) == 0
    r = _run("-m", "neuralbokeh.evaluation", "--data", str(tmp_path / "d"), "--models", str(busy_onnx), "--baselines", "none",
             "--split", "all", "--out", str(tmp_path / "r"))
    _one_error_line(r, "is for 40x32 images, the data is 24x16")


def test_verbose_shows_the_traceback(tmp_path):
    not_a_checkpoint = tmp_path / "notes.pt"
    not_a_checkpoint.write_text("hello")
    r = _run("export.py", str(not_a_checkpoint), "--out", str(tmp_path / "m.onnx"), "-v")
    assert r.returncode == 2 and "Traceback" in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("error: ")


@pytest.mark.parametrize("tool", ["train.py", "export.py", "-m neuralbokeh.evaluation", "-m neuralbokeh.runtime.composite",
                                  "-m data_tools.synth", "-m data_tools.demo_composite", "-m data_tools.raw"])
def test_every_option_has_help(tool):
    import re

    r = _run(*tool.split(), "--help")
    assert r.returncode == 0
    # an option line followed directly by the next option line has no help text
    options = re.findall(r"^  (-[^\n]*)\n(?=  -|\Z)", r.stdout, flags=re.M)
    bare = [o for o in options if "  " not in o.strip()]
    assert not bare, bare
    assert "(default: None)" not in r.stdout
