from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    """``../shared/data`` beside the checkout; skips when a clone does not have it."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"reference data folder {SHARED_DATA} is absent (only the project's own machines have it)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    """A 5-scene, 3-slice, 40x32 synthetic dataset made by the real CLI (7-blade aperture, cat-eye)."""
    from data_tools.synth import main

    out = tmp_path_factory.mktemp("data") / "tiny"
    rc = main(["--out", str(out), "--scenes", "5", "--size", "40", "32", "--slices", "3",
               "--aperture", "polygon:7", "--cat-eye", "0.5", "--seed", "7"])
    assert rc == 0
    return out


@pytest.fixture(scope="session")
def trained_checkpoint(tiny_dataset, tmp_path_factory) -> Path:
    """A checkpoint trained by ``train()`` for a few steps on ``tiny_dataset`` (6 tiles of 16 px)."""
    from neuralbokeh.training import load_config, train

    root = tmp_path_factory.mktemp("run")
    cfg_path = root / "cfg.toml"
    cfg_path.write_text(f"""
[data]
roots = ["{tiny_dataset}"]
test_fraction = 0.2
[model]
blocks = "auto"
features = 4
tile = 16
overlap = 4
[train]
steps = 3
batch_size = 2
lr = 1e-3
eval_every = 3
checkpoint_every = 3
out_dir = "{root / 'run'}"
threads = 1
""")
    return Path(train(load_config(cfg_path), progress=False)["checkpoint"])


@pytest.fixture(scope="session")
def busy_checkpoint(trained_checkpoint, tmp_path_factory) -> Path:
    """``trained_checkpoint`` with C2 and every second convolution set to seeded random values, so
    the network is far from the identity it starts as (parity and stability need a busy network)."""
    import torch

    from neuralbokeh.training.checkpoint import load_checkpoint, save_checkpoint

    data = load_checkpoint(trained_checkpoint)
    g = torch.Generator().manual_seed(11)
    state = dict(data["model_state"])
    for name, t in state.items():
        if name.startswith("c2.") or ".conv_b." in name:
            state[name] = 0.3 * torch.randn(t.shape, generator=g, dtype=t.dtype) / max(1, t[0].numel()) ** 0.5
    data["model_state"] = state
    path = tmp_path_factory.mktemp("busy") / "busy.pt"
    save_checkpoint(path, {k: v for k, v in data.items() if k not in ("format", "format_version", "package_version")})
    return path


@pytest.fixture(scope="session")
def busy_onnx(busy_checkpoint, tmp_path_factory) -> Path:
    """``busy_checkpoint`` exported to ONNX with direct kernels."""
    from neuralbokeh.export.exporter import export_checkpoint

    path = tmp_path_factory.mktemp("onnx") / "busy.onnx"
    export_checkpoint(busy_checkpoint, path, kernels="direct", threads=1)
    return path
