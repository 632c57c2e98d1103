"""Bad data is found before any work is spent on it; runs never lose or overwrite work silently."""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from neuralbokeh.checkpoint import load_checkpoint
from neuralbokeh.core.io import read_image, write_image
from neuralbokeh.data.check import check_dataset
from neuralbokeh.data.dataset import read_scene_meta
from neuralbokeh.training import load_config, train
from neuralbokeh.training import loop as loop_module

ROOT = Path(__file__).resolve().parents[1]


def _config(out: Path, data: Path, steps: int = 4):
    out.mkdir(parents=True, exist_ok=True)
    (out / "cfg.toml").write_text(f"""
[data]
roots = ["{data}"]
test_fraction = 0.2
[model]
blocks = "auto"
tile = 16
overlap = 4
[train]
steps = {steps}
batch_size = 2
lr = 1e-3
eval_every = 100
checkpoint_every = 100
out_dir = "{out / 'run'}"
threads = 1
""")
    return load_config(out / "cfg.toml")


@pytest.fixture
def broken(tiny_dataset, tmp_path) -> tuple[Path, dict[str, Path]]:
    """A copy of the tiny dataset with one fault per scene: truncated EXR, negative depth, NaN
    colour, a CoC map from another focus distance, a wrong image size."""
    root = tmp_path / "broken"
    shutil.copytree(tiny_dataset, root)
    scenes = sorted(p for p in root.iterdir() if p.is_dir())
    bad = {}
    meta = [read_scene_meta(s) for s in scenes]
    path = scenes[0] / meta[0]["slices"][1]["defocus"]
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    bad["truncated"] = path
    path = scenes[1] / meta[1]["files"]["depth"]
    depth = read_image(path)
    depth[3, 5] = -1.0
    write_image(path, depth)
    bad["depth"] = path
    path = scenes[2] / meta[2]["files"]["aif"]
    aif = read_image(path)
    aif[7, 2, 1] = np.nan
    write_image(path, aif)
    bad["nan"] = path
    path = scenes[3] / meta[3]["slices"][0]["coc"]
    write_image(path, read_image(path) * 1.1)
    bad["coc"] = path
    path = scenes[4] / meta[4]["slices"][2]["coc"]
    write_image(path, read_image(path)[:-1])
    bad["size"] = path
    return root, bad


def test_the_check_names_every_bad_file_and_passes_sound_data(tiny_dataset, broken):
    assert check_dataset(tiny_dataset) == []
    root, bad = broken
    problems = check_dataset(root)
    text = "\n".join(problems)
    for kind, path in bad.items():
        assert str(path) in text, kind
    assert "depth must be > 0 m" in text and "-1.0" in text and "(row 3, col 5)" in text
    assert "non-finite colour" in text and "(row 7, col 2)" in text
    assert "CoC differs from the lens and focus" in text
    assert "shape (H, W, C)" in text and "unreadable" in text
    r = subprocess.run([sys.executable, "-m", "neuralbokeh.data", "check", str(root)], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 1 and f"{len(problems)} problem(s)" in r.stdout
    assert all(str(p) in r.stdout for p in bad.values())


def test_train_refuses_bad_data_before_any_step(broken, tmp_path):
    root, bad = broken
    with pytest.raises(ValueError, match="dataset check failed") as e:
        train(_config(tmp_path / "a", root), progress=False)
    assert str(bad["truncated"]) in str(e.value)
    assert not (tmp_path / "a" / "run").exists()  # nothing was started


def test_a_run_never_overwrites_another_and_a_dying_run_keeps_its_steps(tiny_dataset, tmp_path, monkeypatch):
    cfg = _config(tmp_path / "a", tiny_dataset, steps=3)
    train(cfg, progress=False)
    with pytest.raises(ValueError, match="already holds a run .* --resume .* --overwrite"):
        train(cfg, progress=False)
    # Ctrl-C at step 3 of 5: the checkpoint holds step 2 and --resume finishes the run
    real, calls = loop_module.compute_loss, {"n": 0}

    def interrupt_at_3(model, x, y, kind, window=None, weights=None, **kw):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(model, x, y, kind, window, weights, **kw)

    monkeypatch.setattr(loop_module, "compute_loss", interrupt_at_3)
    cfg = _config(tmp_path / "a", tiny_dataset, steps=5)
    with pytest.raises(KeyboardInterrupt):
        train(cfg, progress=False, overwrite=True)
    ck = tmp_path / "a" / "run" / "checkpoint.pt"
    assert load_checkpoint(ck)["step"] == 2
    monkeypatch.setattr(loop_module, "compute_loss", real)
    summary = train(cfg, resume=ck, progress=False)
    assert summary["steps"] == 5 and load_checkpoint(ck)["step"] == 5
    assert torch.isfinite(torch.tensor(summary["metrics"]["eval_psnr"]))


def test_a_rerun_with_another_lens_is_refused_and_mixed_lenses_are_flagged(tmp_path):
    """``synth`` into a folder of scenes made with another size, lens or aperture refuses (it would
    mix two datasets); the check flags scenes that do not share one lens, even when every scene
    alone is sound."""
    import shutil

    from data_tools.synth import main as synth
    from neuralbokeh.data.check import check_dataset

    base = ["--scenes", "2", "--size", "24", "16", "--slices", "1", "--seed", "1"]
    assert synth(["--out", str(tmp_path / "a"), *base]) == 0
    for change, said in ((["--f-number", "4.0"], "lens"), (["--size", "32", "16"], "image_size"),
                         (["--aperture", "polygon:6"], "aperture")):
        with pytest.raises(SystemExit, match=f"holds 2 scene\\(s\\) of another {said}.*choose another --out"):
            synth(["--out", str(tmp_path / "a"), *base, *change])
    assert len(list((tmp_path / "a").glob("scene_*"))) == 2
    assert synth(["--out", str(tmp_path / "b"), *base, "--f-number", "4.0"]) == 0
    assert check_dataset(tmp_path / "a") == [] and check_dataset(tmp_path / "b") == []
    shutil.copytree(tmp_path / "b" / "scene_00000", tmp_path / "a" / "scene_00009")
    problems = check_dataset(tmp_path / "a")
    assert len(problems) == 1 and "the scenes have 2 different lenses" in problems[0] and "scene_00009" in problems[0]
