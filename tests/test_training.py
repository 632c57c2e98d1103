import dataclasses
import json
import math
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import torch

from neuralbokeh.checkpoint import load_model
from neuralbokeh.core.apertures import ApertureModel
from neuralbokeh.core.apertures.shapes import Polygon
from neuralbokeh.core.contract import Contract
from neuralbokeh.core.normalization import Normalization
from neuralbokeh.data.dataset import FocalStackDataset
from neuralbokeh.networks import build_model
from neuralbokeh.networks.config import ModelConfig
from neuralbokeh.training import load_config, train
from neuralbokeh.training import loop as loop_module
from neuralbokeh.training.config import build_config
from neuralbokeh.training.loop import Samples, held_out_metrics

ROOT = Path(__file__).resolve().parents[1]


def _config(tmp_path, data, **train_overrides):
    text = f"""
[data]
roots = ["{data}"]
test_fraction = 0.2
cache = true

[model]
blocks = "auto"
features = 4
tile = 16
overlap = 4

[train]
steps = 4
batch_size = 2
lr = 1e-3
warmup_steps = 1
eval_every = 2
checkpoint_every = 2
seed = 3
out_dir = "{tmp_path / 'run'}"
threads = 1
"""
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = tmp_path / "cfg.toml"
    path.write_text(text)
    return load_config(path, [f"train.{k}={v}" for k, v in train_overrides.items()])


# --- configs -------------------------------------------------------------------------------------


def test_a_stored_model_config_reads_back_with_the_dataclass_defaults():
    cfg = ModelConfig(blocks=3, tile=16, overlap=4, pupil_init="disk")
    assert ModelConfig.from_dict(cfg.to_dict()) == cfg
    assert ModelConfig.from_dict({"blocks": 3, "near_focus_px": 4.0, "pixel_blur": False, "surface_fill": True,
                                  "occlusion_margin_learned": True, "occlusion_margin_step": False, "occlusion_margin_slope": True,
                                  "occlusion_source_coc": True, "field_flow": False, "field_gradient": True,
                                  "occlusion_source_coc_grid": 2, "highlight_spread": True}) == ModelConfig(blocks=3)
    # keys whose defaults changed since: left out, they mean what they meant then (a uniform
    # lattice, no pixel blur, the sharp fill, a fixed margin without floors, each tile's light
    # where its pupil puts it, highlights rasterised as every pixel)
    then = {"near_focus_px": 0.0, "pixel_blur": False, "surface_fill": False, "occlusion_margin_learned": False,
            "occlusion_margin_step": False, "occlusion_margin_slope": False, "occlusion_source_coc": False, "field_gradient": False,
            "occlusion_source_coc_grid": 1, "highlight_spread": False}
    assert ModelConfig.from_dict({"blocks": 3}) == ModelConfig(blocks=3, field_flow=False, **then)
    # a checkpoint from when the flow was the default: the flow, not today's gradient
    assert ModelConfig.from_dict({"blocks": 3, "field_flow": True}) == ModelConfig(blocks=3, field_flow=True, **then)
    with pytest.raises(ValueError, match="model.field_flow must be true or false, got 1"):
        ModelConfig(blocks=3, field_flow=1)
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match=f"model.occlusion_source_coc_grid must be an integer >= 1, got {bad!r}"):
            ModelConfig(blocks=3, occlusion_source_coc_grid=bad)
    with pytest.raises(ValueError, match=r"unknown model config keys \['kernels'\]"):
        ModelConfig.from_dict({"blocks": 3, "kernels": "growing"})


def test_shipped_configs_load_and_ablations_differ_as_named():
    base = load_config(ROOT / "configs" / "quickstart.toml")
    assert base.model.blocks == "auto" and base.train.loss == "image"
    paper = load_config(ROOT / "configs" / "paper.toml")
    assert (paper.model.tile, paper.model.overlap) == (200, 60)
    expected = {
        "fixed3_kernels": ("model", "kernel_sizes", "fixed3"),
        "no_tiling": ("model", "tiling", "none"),
        "no_overlap": ("model", "tiling", "no_overlap"),
        "tile_loss": ("train", "loss", "tile"),
        "paper_head": ("model", "head", "paper"),
        "paper_network": ("model", "architecture", "paper"),
    }
    for name, (section, key, value) in expected.items():
        cfg = load_config(ROOT / "configs" / "ablations" / f"{name}.toml")
        assert getattr(getattr(cfg, section), key) == value
        assert cfg.data.roots == base.data.roots and cfg.train.steps == base.train.steps
        assert cfg.train.out_dir == f"runs/{name}"


def test_config_errors(tmp_path):
    good = ROOT / "configs" / "quickstart.toml"
    with pytest.raises(ValueError, match=r"command-line override 'train.stepz=3': unknown key 'stepz' in \[train\]"):
        load_config(good, ["train.stepz=3"])
    with pytest.raises(TypeError, match="train.steps must be int, got 'ten'"):
        load_config(good, ["train.steps=ten"])
    with pytest.raises(TypeError, match="train.lr must be float"):
        load_config(good, ["train.lr=true"])
    with pytest.raises(ValueError, match="model.tiling must be one of"):
        load_config(good, ["model.tiling=grid"])
    with pytest.raises(ValueError, match="section.key=value"):
        load_config(good, ["steps=3"])
    with pytest.raises(ValueError, match=r"command-line override 'optim.lr=1.0': unknown section 'optim'"):
        load_config(good, ["optim.lr=1.0"])
    (tmp_path / "typo.toml").write_text('extends = "%s"\n[train]\nstepz = 3\n' % good)
    with pytest.raises(ValueError, match=r"typo.toml: unknown key\(s\) \['stepz'\] in \[train\]"):  # in a file: the file
        load_config(tmp_path / "typo.toml")
    assert load_config(good, ["train.lr=1", "data.roots=['a', 'b']"]).train.lr == 1.0
    (tmp_path / "a.toml").write_text('extends = "b.toml"\n')
    (tmp_path / "b.toml").write_text('extends = "a.toml"\n')
    with pytest.raises(ValueError, match="extends itself"):
        load_config(tmp_path / "a.toml")
    with pytest.raises(FileNotFoundError, match="no such config"):
        load_config(tmp_path / "missing.toml")
    with pytest.raises(ValueError, match=r"train.ssim_weight must be a finite number >= 0, got -0.5"):
        load_config(good, ["train.ssim_weight=-0.5"])
    with pytest.raises(ValueError, match=r"train.pupil_tv must be a finite number >= 0, got -1.0"):
        load_config(good, ["train.pupil_tv=-1.0"])
    with pytest.raises(ValueError, match=r"train.pupil_tv needs the lens architecture .*'paper'"):
        load_config(good, ["train.pupil_tv=0.1", "train.pupil_chroma=0", "model.architecture='paper'"])
    with pytest.raises(ValueError, match=r"train.pupil_chroma must be a finite number >= 0, got nan"):
        load_config(good, ["train.pupil_chroma=nan"])
    with pytest.raises(ValueError, match=r"train.pupil_chroma needs the lens architecture .*'paper'"):
        load_config(good, ["train.pupil_chroma=0.1", "train.pupil_tv=0", "model.architecture='paper'"])
    with pytest.raises(ValueError, match=r"train.pupil_field_spread needs the lens architecture .*'paper'"):
        load_config(good, ["train.pupil_tv=0", "train.pupil_chroma=0", "model.architecture='paper'"])
    with pytest.raises(ValueError, match=r"train.loss_pool must be an integer >= 1 \(px\), got 0"):
        load_config(good, ["train.loss_pool=0"])
    with pytest.raises(TypeError, match=r"train.loss_pool must be int, got 2.5"):
        load_config(good, ["train.loss_pool=2.5"])
    with pytest.raises(ValueError, match=r"train.ema_steps must be an integer >= 0 \(steps; 0: off\), got -1"):
        load_config(good, ["train.ema_steps=-1"])
    with pytest.raises(ValueError, match=r"train.loss_pool = 2 needs train.loss = 'image' .*got 'tile'"):
        load_config(good, ["train.loss_pool=2", "train.loss='tile'"])


# --- training ------------------------------------------------------------------------------------


def test_train_writes_checkpoint_log_and_metrics(tiny_dataset, tmp_path):
    cfg = _config(tmp_path, tiny_dataset)
    summary = train(cfg, progress=False)
    ck_path = Path(summary["checkpoint"])
    model, ck = load_model(ck_path)
    assert isinstance(model.config, ModelConfig) and model.contract.size == (32, 40)
    assert ck["model_config"]["blocks"] == 6  # max |CoC| 8.0 px -> N = 4 on a uniform lattice, 2 more near focus
    contract = ck["contract"]
    assert contract["lens"]["focal_length_mm"] == 85.0 and contract["aperture"]["cat_eye"] == 0.5
    assert contract["normalization"]["kind"] == "mobius-log" and contract["coc_scale_px"] > 1
    assert Contract.from_dict(contract) == model.contract
    m = summary["metrics"]
    # the lens network starts as a CoC scatter renderer: it blurs, so it is ahead of the AIF
    # returned unchanged, as the Gaussian and the exact-aperture oracle are; SSIM is in (0, 1]
    assert min(m["eval_psnr"], m["gaussian_psnr"], m["oracle_psnr"]) > m["identity_psnr"]
    assert all(0.0 < m[k] <= 1.0 for k in ("eval_ssim", "identity_ssim", "gaussian_ssim", "oracle_ssim"))
    rows = (tmp_path / "run" / "log.csv").read_text().splitlines()
    assert rows[0].startswith("step,loss,lr,skipped") and len(rows) == 5
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["steps"] == 4


@pytest.mark.parametrize("ema_steps", [0, 2])
def test_resume_continues_bit_for_bit(tiny_dataset, tmp_path, ema_steps):
    straight = train(_config(tmp_path / "a", tiny_dataset, steps=6, ema_steps=ema_steps), progress=False)
    first = train(_config(tmp_path / "b", tiny_dataset, steps=6, ema_steps=ema_steps), progress=False, stop_at=3)
    assert first["steps"] == 3
    resumed = train(_config(tmp_path / "b", tiny_dataset, steps=6, ema_steps=ema_steps), resume=first["checkpoint"],
                    progress=False)
    a = torch.load(straight["checkpoint"], weights_only=False)
    b = torch.load(resumed["checkpoint"], weights_only=False)
    assert a["step"] == b["step"] == 6
    states = ("model_state", "trained_state") if ema_steps else ("model_state",)
    assert all(s in a for s in states) and ("trained_state" in a) == bool(ema_steps)
    for state in states:
        for key, value in a[state].items():
            assert torch.equal(value, b[state][key]), (state, key)
    if ema_steps:  # the model is the average, not the last step's weights; evaluated and loaded as such
        assert not torch.equal(a["model_state"]["log_channel_scale"], a["trained_state"]["log_channel_scale"])
        model, _ = load_model(straight["checkpoint"])
        assert torch.equal(model.log_channel_scale.detach(), a["model_state"]["log_channel_scale"])
    assert a["metrics"] == b["metrics"]


def test_moving_average_is_the_mean_then_exponential():
    """train.ema_steps = 3: after n updates the average is the plain mean of the n weights while
    n <= 3, then each update moves it a third of the way to the new weights."""
    net = torch.nn.Linear(1, 1, bias=False)
    ema = loop_module.averaged(net, 3)
    assert not any(p.requires_grad for p in ema.parameters())
    values = [1.0, 2.0, 6.0, 10.0, 4.0]
    expect = [1.0, 1.5, 3.0, 3.0 + (10.0 - 3.0) / 3, None]
    expect[4] = expect[3] + (4.0 - expect[3]) / 3
    for v, e in zip(values, expect):
        with torch.no_grad():
            net.weight.fill_(v)
        ema.update_parameters(net)
        assert ema.module.weight.item() == pytest.approx(e, rel=1e-6)
    assert loop_module.ema_weight(torch.tensor(0), 3).item() == 1.0
    assert loop_module.ema_weight(torch.tensor(10), 3).item() == pytest.approx(1 / 3)


def test_resume_refuses_another_model(tiny_dataset, tmp_path):
    first = train(_config(tmp_path / "a", tiny_dataset, steps=2), progress=False)
    other = _config(tmp_path / "b", tiny_dataset, steps=4)
    other.model = dataclasses.replace(other.model, features=5)
    with pytest.raises(ValueError, match="checkpoint .* is for model"):
        train(other, resume=first["checkpoint"], progress=False)


def test_resume_refuses_to_write_into_another_run(tiny_dataset, tmp_path):
    done = train(_config(tmp_path / "a", tiny_dataset, steps=2), progress=False)
    partial = train(_config(tmp_path / "b", tiny_dataset, steps=4), progress=False, stop_at=2)
    before = (tmp_path / "a" / "run" / "checkpoint.pt").read_bytes()
    with pytest.raises(ValueError, match="another run's checkpoint"):  # b's checkpoint resumed into a's folder
        train(_config(tmp_path / "a", tiny_dataset, steps=4), resume=partial["checkpoint"], progress=False)
    assert (tmp_path / "a" / "run" / "checkpoint.pt").read_bytes() == before  # a's finished run is intact
    assert Path(done["checkpoint"]).is_file()
    # into an empty folder, another run's checkpoint continues (a fork); into its own, as always
    forked = train(_config(tmp_path / "c", tiny_dataset, steps=4), resume=partial["checkpoint"], progress=False)
    assert forked["steps"] == 4


def test_crops_of_scenes_of_mixed_sizes_train_and_evaluate_on_whole_frames(tiny_dataset, tmp_path):
    """Scenes of two sizes in one dataset train on random 24x32 crops (each with its sensor window);
    held-out evaluation runs on the whole frames; a resumed run cuts the same crops."""
    from data_tools.synth import main as synth

    other = tmp_path / "other"
    assert synth(["--out", str(other), "--scenes", "3", "--size", "48", "36", "--slices", "3",
                  "--aperture", "polygon:7", "--cat-eye", "0.5", "--seed", "9"]) == 0
    roots = [f"'{tiny_dataset}'", f"'{other}'"]

    def config(name, *extra):
        _config(tmp_path / name, tiny_dataset)  # writes its cfg.toml
        return load_config(tmp_path / name / "cfg.toml", [f"data.roots=[{', '.join(roots)}]", *extra])

    with pytest.raises(ValueError, match="must share 'image_size'"):  # whole scenes of two sizes: refused, named
        train(config("whole"), progress=False)
    straight = train(config("a", "data.crop=[24, 32]"), progress=False)
    model, ck = load_model(straight["checkpoint"])
    assert model.contract.size == (24, 32)  # the crop: what the weights were fitted on
    sizes = {tuple(FocalStackDataset(r.strip("'"), "all")[0]["aif"].shape[-2:]) for r in roots}
    assert sizes == {(32, 40), (36, 48)}
    assert straight["metrics"]["eval_psnr"] > straight["metrics"]["identity_psnr"]  # whole held-out frames
    # a crop read from disk (its rows only) is the crop cut from the cached scene
    ds = FocalStackDataset([r.strip("'") for r in roots], "train")
    cached, read = (Samples(ds, cache, [24, 32]).batch(list(range(0, len(ds), 3)), torch.device("cpu"), seed=7)
                    for cache in (True, False))
    assert torch.equal(cached[0], read[0]) and torch.equal(cached[1], read[1]) and cached[2] == read[2]
    assert torch.allclose(cached[3], read[3], atol=1e-6) and (cached[3][:, 2:] < 1).all()  # windows: crops of the sensor
    assert torch.equal(cached[4], read[4]) and cached[4].any()  # the sides each crop cuts through its frame
    first = train(config("b", "data.crop=[24, 32]"), progress=False, stop_at=2)
    resumed = train(config("b", "data.crop=[24, 32]"), resume=first["checkpoint"], progress=False)
    b = torch.load(resumed["checkpoint"], weights_only=False)
    for key, value in ck["model_state"].items():
        assert torch.equal(value, b["model_state"][key]), key


def test_non_finite_steps_are_skipped_then_abort(tiny_dataset, tmp_path, monkeypatch):
    real = loop_module.compute_loss
    calls = {"n": 0}

    def nan_on_steps_2_and_3(model, x, y, kind, window=None, weights=None, **kw):
        calls["n"] += 1
        loss = real(model, x, y, kind, window, weights, **kw)
        return loss * float("nan") if calls["n"] in (2, 3) else loss

    monkeypatch.setattr(loop_module, "compute_loss", nan_on_steps_2_and_3)
    summary = train(_config(tmp_path / "a", tiny_dataset, steps=5, max_nonfinite=3), progress=False)
    assert summary["skipped_steps"] == 2
    log = (tmp_path / "a" / "run" / "log.csv").read_text().splitlines()
    assert [r.split(",")[3] for r in log[1:]] == ["0", "1", "2", "2", "2"]

    monkeypatch.setattr(loop_module, "compute_loss", lambda m, x, y, k, w=None, lw=None, **kw: real(m, x, y, k, w, lw, **kw) * float("inf"))
    with pytest.raises(RuntimeError, match=r"3 non-finite steps in a row, the last at step 3 \(batch scenes on rank 0: scene_000"):
        train(_config(tmp_path / "b", tiny_dataset, steps=5, max_nonfinite=3), progress=False)


@pytest.mark.parametrize("ablation", ["fixed3_kernels", "no_tiling", "no_overlap", "tile_loss", "paper_head", "paper_network"])
def test_ablations_train(tiny_dataset, tmp_path, ablation):
    cfg = load_config(
        ROOT / "configs" / "ablations" / f"{ablation}.toml",
        [f"data.roots=['{tiny_dataset}']", "train.steps=2", "train.batch_size=2", "train.eval_every=2",
         f"train.out_dir='{tmp_path}'", "model.tile=16", "model.overlap=4", "model.features=3"],
    )
    summary = train(cfg, progress=False)
    # the checkpoint rebuilds this ablation's network (its own [model] keys), and that network
    # gives the held-out PSNR the run reported
    model, ck = load_model(summary["checkpoint"])
    declared = tomllib.loads((ROOT / "configs" / "ablations" / f"{ablation}.toml").read_text()).get("model", {})
    for key, value in declared.items():
        assert getattr(model.config, key) == value, (ablation, key)
    assert ck["train_config"]["train"]["loss"] == cfg.train.loss
    test = FocalStackDataset(tiny_dataset, "test", cfg.data.test_fraction, cfg.data.split_seed,
                             normalization=Normalization(cfg.data.normalization_scale))
    again = held_out_metrics(model, Samples(test, cache=False), torch.device("cpu"), baselines={})
    assert again["eval_psnr"] == pytest.approx(summary["metrics"]["eval_psnr"], abs=1e-4)


def test_two_processes_hold_identical_weights(tiny_dataset, tmp_path):
    cfg = _config(tmp_path, tiny_dataset, steps=3)  # validates the file
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nnodes=1", "--nproc_per_node=2",
           str(ROOT / "train.py"), str(tmp_path / "cfg.toml"), "train.steps=3"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((Path(cfg.train.out_dir) / "summary.json").read_text())
    assert summary["world_size"] == 2
    digests = summary["rank_weight_digests"]
    assert len(digests) == 2 and digests[0] == digests[1]
    assert "checkpoint" in proc.stdout


def test_time_limit_stops_with_evaluation_and_checkpoint(tiny_dataset, tmp_path):
    summary = train(_config(tmp_path, tiny_dataset, steps=50, eval_every=40), progress=False, time_limit_s=0.0)
    assert summary["steps"] == 1 and "eval_psnr" in summary["metrics"]
    assert torch.load(summary["checkpoint"], weights_only=False)["step"] == 1


def test_model_table_is_the_model_config():
    # [model] of a training config is ModelConfig itself: one class, "auto" blocks resolved from the data
    cfg = build_config({"data": {"roots": ["x"]}, "model": {"blocks": "auto", "tile": 32, "overlap": 8}})
    assert isinstance(cfg.model, ModelConfig) and cfg.model.blocks == "auto"
    assert cfg.model.resolved(8.0).blocks == 6 and cfg.model.resolved(8.0).tile == 32  # 4 on a uniform lattice, 2 near focus
    with pytest.raises(ValueError, match="model.tiling must be one of"):
        build_config({"data": {"roots": ["x"]}, "model": {"tiling": "grid"}})


def test_large_kernels_learn_at_lr_over_fan_in():
    from neuralbokeh.networks.paper import PaperBokeh
    from neuralbokeh.training.loop import param_groups

    model = PaperBokeh(ModelConfig(blocks=3, features=2, tile=16, overlap=0, architecture="paper"),
                        Contract(16, 16, Normalization(), 1.0, 1.0))
    groups = param_groups(model, "fan_in")
    scales = {g["lr_scale"]: sum(p.numel() for p in g["params"]) for g in groups}
    assert set(scales) == {1.0, 1 / 9, 1 / 25, 1 / 49}  # 1x1 convs and biases at 1; k x k kernels at 1/k^2
    assert sum(scales.values()) == sum(p.numel() for p in model.parameters())
    assert [g["lr_scale"] for g in param_groups(model, "none")] == [1.0]


def test_ablation_runner_writes_table_one(tiny_dataset, tmp_path):
    from neuralbokeh.evaluation.ablations import VARIANTS, main

    cfg = _config(tmp_path / "cfg", tiny_dataset)
    path = tmp_path / "cfg" / "cfg.toml"
    assert cfg.train.steps == 4
    rc = main([str(path), "train.steps=2", "--data", str(tiny_dataset), "--out", str(tmp_path / "abl"), "--minutes", "0",
               "--samples", "2", "--threads", "1"])
    assert rc == 0
    rows = json.loads((tmp_path / "abl" / "table.json").read_text())
    assert [r["variant"] for r in rows] == list(VARIANTS) and all(r["steps"] == 2 for r in rows)
    table = (tmp_path / "abl" / "table.md").read_text()
    assert "| 3x3 kernel size |" in table and "| Loss per tile |" in table
    assert json.loads((tmp_path / "abl" / "no_tiling" / "summary.json").read_text())["model"]["tiling"] == "none"


def test_the_crop_loss_leaves_out_just_the_light_a_crop_cannot_see():
    """Next to a side where a crop cuts its frame, the whole frame's defocus holds light from
    beyond the crop: the reference renderer fed the crop alone misses it there, and only there.
    The loss weights drop exactly that band (the largest CoC radius) on cut sides and keep the
    frame's own borders, where the crop and the frame see the same."""
    from neuralbokeh.core.apertures import ApertureModel, Disk
    from neuralbokeh.data.dataset import cut_sides
    from neuralbokeh.render import scatter_defocus
    from neuralbokeh.training.loop import crop_loss_margin, loss_weights

    g = torch.Generator().manual_seed(3)
    h_full, w_full, c_max = 60, 72, 9.0
    img = 0.18 * torch.exp2(4 * torch.rand(1, 3, h_full, w_full, generator=g, dtype=torch.float64) - 2)
    img[..., 2::7, 3::9] = 50.0  # highlights everywhere, the frame's edges included
    coc = torch.full((1, 1, h_full, w_full), c_max, dtype=torch.float64)
    disk = ApertureModel(Disk())
    truth = scatter_defocus(img, coc, disk)
    margin = crop_loss_margin([32, 40], c_max)
    assert margin == 5
    for r0, c0 in ((14, 20), (0, 0), (28, 32)):  # inside, the top-left corner, the bottom-right corner
        rows, cols = (r0, r0 + 32), (c0, c0 + 40)
        pred = scatter_defocus(img[..., slice(*rows), slice(*cols)], coc[..., slice(*rows), slice(*cols)], disk)
        err = (pred - truth[..., slice(*rows), slice(*cols)]).abs().amax(1, keepdim=True)
        cut = cut_sides(rows, cols, h_full, w_full)[None]
        w = loss_weights(cut, (32, 40), margin)
        assert float((err * w).max()) < 1e-9, (r0, c0)  # what the loss keeps, the crop can render exactly
        assert float((err * (1 - w)).max()) > 1e-2, (r0, c0)  # what it drops held light from beyond the crop
        assert float(w.mean()) == pytest.approx((32 - margin * int(cut[0, :2].sum())) * (40 - margin * int(cut[0, 2:].sum())) / (32 * 40))
    assert loss_weights(torch.zeros(2, 4, dtype=torch.bool), (32, 40), margin) is None  # whole frames: all pixels
    with pytest.raises(ValueError, match=r"data.crop = \[8, 40\] px leaves no pixel for the loss"):
        crop_loss_margin([8, 40], c_max)
    assert crop_loss_margin([32, 40], c_max, 0) == 0 and crop_loss_margin([32, 40], c_max, 7) == 7  # data.crop_margin
    assert crop_loss_margin([], c_max) == 0  # whole scenes
    with pytest.raises(ValueError, match="data.crop_margin must be an integer >= 0"):
        build_config({"data": {"roots": ["data"], "crop_margin": -2}})


def test_the_ssim_term_is_the_evaluation_ssim_on_the_pixels_the_loss_keeps():
    """``train.ssim_weight`` adds ``w (1 - SSIM)``, the held-out metric's SSIM (kornia, 11 px),
    over the same pixels as the MSE; 0 leaves the MSE alone."""
    from kornia.losses import ssim_loss
    from kornia.metrics import ssim

    cfg = ModelConfig(tile=16, overlap=4).resolved(8.0)
    model = build_model(cfg, Contract(24, 24, Normalization(), 8.0, 8.0)).eval()
    g = torch.Generator().manual_seed(5)
    x = torch.cat([torch.rand(2, 3, 24, 24, generator=g) * 1.8 - 0.9, torch.rand(2, 1, 24, 24, generator=g) * 2 - 1], 1)
    y = torch.rand(2, 3, 24, 24, generator=g) * 1.8 - 0.9
    with torch.no_grad():
        pred = model(x)
        mse = loop_module.compute_loss(model, x, y, "image")
        both = loop_module.compute_loss(model, x, y, "image", ssim_weight=0.5)
        ssim_term = 2.0 * ssim_loss((pred + 1) / 2, (y + 1) / 2, 11)  # kornia's loss is (1 - SSIM) / 2
        torch.testing.assert_close(mse, torch.nn.functional.mse_loss(pred, y))
        torch.testing.assert_close(both - mse, 0.5 * ssim_term, rtol=1e-5, atol=1e-7)
        # with crop weights, both terms average over the kept pixels only
        w = torch.zeros(2, 1, 24, 24)
        w[..., 4:20, 4:20] = 1.0
        kept = loop_module.compute_loss(model, x, y, "image", weights=w, ssim_weight=0.5)
        s_map = 1.0 - ssim((pred + 1) / 2, (y + 1) / 2, 11)
        want = (((pred - y).square() + 0.5 * s_map) * w).sum() / (w.sum() * 3)
        torch.testing.assert_close(kept, want, rtol=1e-5, atol=1e-7)


def test_a_pooled_loss_averages_in_linear_light_over_the_kept_pixels():
    """``train.loss_pool``: MSE and SSIM of the images averaged over k x k px blocks in linear
    light (a partial block at the edge averages what it holds), the crop weights averaged alike;
    the block mean of a noisy target is about k^2 times less darkened by the normalisation."""
    from kornia.metrics import ssim

    norm = Normalization()
    cfg = ModelConfig(tile=16, overlap=4).resolved(8.0)
    model = build_model(cfg, Contract(26, 26, norm, 8.0, 8.0)).eval()
    g = torch.Generator().manual_seed(5)
    x = torch.cat([torch.rand(2, 3, 26, 26, generator=g) * 1.8 - 0.9, torch.rand(2, 1, 26, 26, generator=g) * 2 - 1], 1)
    y = torch.rand(2, 3, 26, 26, generator=g) * 1.8 - 0.9
    w = torch.zeros(2, 1, 26, 26)
    w[..., 4:20, 4:24] = 1.0
    with torch.no_grad():
        pred = model(x)
        got = loop_module.compute_loss(model, x, y, "image", weights=w, ssim_weight=0.5, pool=4, normalization=norm)
    def pooled(n):  # 26 px: six whole blocks and one of 2 px
        lin = norm.decode(n.double())
        cols = torch.stack([lin[..., :, j * 4:j * 4 + 4].mean(-1) for j in range(7)], -1)
        return norm.encode(torch.stack([cols[..., i * 4:i * 4 + 4, :].mean(-2) for i in range(7)], -2)).float()
    pw = torch.stack([torch.stack([w[..., i * 4:i * 4 + 4, j * 4:j * 4 + 4].mean((-2, -1)) for j in range(7)], -1)
                      for i in range(7)], -2)
    p4, y4 = pooled(pred), pooled(y)
    s_map = 1.0 - ssim((p4 + 1) / 2, (y4 + 1) / 2, 11)
    want = (((p4 - y4).square() + 0.5 * s_map) * pw).sum() / (pw.sum() * 3)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-7)
    # the bias: a flat 0.05 under unit relative noise (gamma, heavy-tailed like a render's)
    torch.manual_seed(0)
    clean = torch.full((1, 3, 256, 256), 0.05, dtype=torch.float64)
    noisy = clean * torch.distributions.Gamma(torch.ones_like(clean), torch.ones_like(clean)).sample()
    clean_n = float(norm.encode(torch.tensor(0.05, dtype=torch.float64)))
    bias = [float(loop_module.pool_linear(norm.encode(noisy), k, norm).mean()) - clean_n for k in (1, 4)]
    assert bias[0] < -0.02 and bias[0] / 8 < bias[1] < 0.0  # darker on average; 16x less to first order (measured 13x)


def _fit_one_band(truth: ApertureModel, scale: float, steps: int, noise: float = 0.0,
                  pool: int = 1) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Train an untrained disk-pupil lens network, with the quickstart's optimiser settings, on
    sparse highlights over a dim texture blurred at one constant CoC ``d`` (px) by the ``truth``
    aperture scaled by ``scale`` (its rim at ``scale`` aperture radii). ``noise``: the targets'
    zero-mean noise in linear light, relative (each pixel times a mean-1 gamma variate of that
    standard deviation: heavy-tailed, as a render's); ``pool``: ``train.loss_pool``. Returns the
    learned and the true kernel at ``d`` (behind the focus plane, green, sensor centre;
    ``(k, k)`` each) and d."""
    import torch.nn.functional as F

    from neuralbokeh.training.config import TrainSection
    from neuralbokeh.training.loop import compute_loss, param_groups

    train_cfg = tomllib.loads((ROOT / "configs" / "quickstart.toml").read_text())["train"]
    size, c_max = 48, 11.0
    torch.manual_seed(0)
    # a lattice uniform in the CoC: band 6 at 9.6 px, large enough to show a square's corners
    # one kernel over the whole frame: no field gradient (it would triple the scatters of a test about the pupil)
    model = build_model(ModelConfig(blocks=7, tile=size, overlap=12, pupil_init="disk", near_focus_px=0.0, field_gradient=False),
                        Contract(size, size, Normalization(), c_max, c_max))
    d = float(model.plan(c_max).diameters[6])  # on a band centre: one band's kernel is all that is learned
    true_k = torch.from_numpy(truth.kernels(d * scale)[1]).float()
    g = torch.Generator().manual_seed(1)
    aif = 0.05 * torch.rand(8, 3, size, size, generator=g)
    aif = aif + (torch.rand(8, 1, size, size, generator=g) < 0.01) * 20.0 * torch.rand(8, 3, size, size, generator=g)
    k = true_k.shape[-1]
    target = F.conv2d(aif.reshape(-1, 1, size, size), true_k.flip(-2, -1)[None, None], padding=k // 2).view(8, 3, size, size)
    if noise > 0:
        shape = torch.full_like(target, 1.0 / noise**2)
        target = target * torch.distributions.Gamma(shape, shape).sample()
    norm = model.contract.normalization
    x = torch.cat([norm.encode(aif), torch.full((8, 1, size, size), d / c_max)], 1)
    keep = torch.zeros(8, 1, size, size)
    keep[..., k:-k, k:-k] = 1.0  # away from the frame's edge, where light from outside it is missing
    field_lr_scale = float(train_cfg.get("field_lr_scale", TrainSection.field_lr_scale))
    opt = torch.optim.Adam(param_groups(model, "none", field_lr_scale), lr=train_cfg["lr"])
    for group in opt.param_groups:
        group["lr"] = group["lr_scale"] * train_cfg["lr"]
    for _ in range(steps):
        opt.zero_grad()
        compute_loss(model, x, norm.encode(target), "image", None, keep, pool=pool, normalization=norm).backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), train_cfg["grad_clip"])
        opt.step()
    with torch.no_grad():
        learned = model.kernels(6, model.pupils_at(torch.zeros(1, 1, 2)).flatten(0, 1), d)[0, 0, 1]
    size_k = max(learned.shape[-1], k)
    learned, true_k = (F.pad(t, [(size_k - t.shape[-1]) // 2] * 4) for t in (learned, true_k))  # one size, centred
    return learned, true_k, d


def test_a_disk_is_barely_rough_and_not_coloured_at_all():
    contract = Contract(32, 32, Normalization(), 9.0, 9.0)
    disk = build_model(ModelConfig(tile=16, overlap=4, pupil_init="disk").resolved(9.0), contract)
    assert float(disk.pupil_roughness().detach()) == pytest.approx(0.14, abs=0.02)
    assert float(disk.pupil_chroma().detach()) == pytest.approx(0.0, abs=1e-6)  # float32 rounding of the grey mean
    assert float(disk.pupil_field_spread().detach()) == 0.0  # no field correction at the start
    with torch.no_grad():  # one node of 25 at twice the lens-wide transmission everywhere: 1/25
        disk.pupil_field[0, 0].fill_(math.log(2.0))
    assert float(disk.pupil_field_spread().detach()) == pytest.approx(0.04, rel=1e-5)
    with torch.no_grad():  # CoC scales 1.04 / 1 / 0.96: the mean absolute deviation of their logs
        disk.log_channel_scale.copy_(torch.log(torch.tensor([1.04, 1.0, 0.96])))
    assert float(disk.pupil_chroma().detach()) == pytest.approx(0.0267, abs=2e-4)


@pytest.mark.parametrize(("term", "measure", "start"), [("pupil_tv", "pupil_roughness", 1.0), ("pupil_chroma", "pupil_chroma", 0.5),
                                                   ("pupil_field_spread", "pupil_field_spread", 0.5)])
def test_a_pupil_term_smooths_a_speckled_pupil_in_training(tiny_dataset, tmp_path, term, measure, start):
    """``train.pupil_tv`` / ``train.pupil_chroma`` / ``train.pupil_field_spread``: trained from
    pupils speckled apart in each channel (lens-wide; for the field spread, at each field node),
    the term leaves them smoother / their channels closer / the nodes closer to the lens-wide
    pupil than the same steps without it."""
    seen = {}
    for weight in (0.0, 1.0):
        field_lr = {"field_lr_scale": 1.0} if term == "pupil_field_spread" else {}  # the field learns at lr, not lr / 4
        cfg = _config(tmp_path / str(weight), tiny_dataset, **{term: weight}, lr=0.03, steps=6, eval_every=100, **field_lr)
        torch.manual_seed(0)
        with torch.no_grad():
            noise = torch.randn(25 if term == "pupil_field_spread" else 1, 2, 3, 48, 48, generator=torch.Generator().manual_seed(1))
        real_build = loop_module.build_model

        def speckled(config, contract, noise=noise):  # the run starts from a speckled pupil
            model = real_build(config, contract)
            with torch.no_grad():
                if term == "pupil_field_spread":  # each node of the 5 x 5 field grid its own
                    model.pupil_field.add_(noise.view_as(model.pupil_field))
                else:
                    model.pupil_shared.add_(noise[0])
            return model

        loop_module.build_model = speckled
        try:
            train(cfg, progress=False)
        finally:
            loop_module.build_model = real_build
        model, _ = load_model(tmp_path / str(weight) / "run" / "checkpoint.pt")
        seen[weight] = float(getattr(model, measure)().detach())
    assert seen[1.0] < 0.9 * seen[0.0], seen  # measured 1.88 against 2.16 (rough), 0.52 against 0.63 (colour),
    # 0.91 against 1.14 (field)
    assert seen[0.0] > start, seen  # the start really is speckled


def test_a_disk_pupil_grows_into_a_larger_square_and_shrinks_to_a_smaller_hexagon():
    """The pupil is not stuck where it starts: log-transmissions at the floor outside the start's
    disk still learn (Adam's steps do not scale with the tiny gradient there)."""
    learned, truth, d = _fit_one_band(ApertureModel(Polygon(4, 45.0)), 1.2, steps=120)  # corners at 1.2 radii
    start, _, _ = _fit_one_band(ApertureModel(Polygon(4, 45.0)), 1.2, steps=0)
    r = torch.arange(truth.shape[-1]) - truth.shape[-1] // 2
    corners = (r[:, None] ** 2 + r[None, :] ** 2).float().sqrt() >= d / 2 + 0.75  # beyond the start disk's anti-aliased rim
    assert float(start[corners].sum()) < 1e-3 < 0.015 < float(truth[corners].sum())
    assert float((learned - truth).abs().sum()) <= 0.04 < 0.2 <= float((start - truth).abs().sum())
    assert float(learned[corners].sum()) == pytest.approx(float(truth[corners].sum()), rel=0.3)
    learned, truth, _ = _fit_one_band(ApertureModel(Polygon(6)), 0.6, steps=120)  # inside the start's disk
    assert float((learned - truth).abs().sum()) <= 0.04
