import os
from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    """``../shared/data`` beside the checkout; skips when a clone does not have it."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"reference data folder {SHARED_DATA} is absent (only the project's own machines have it)")
    return SHARED_DATA


def pytest_collection_modifyitems(config, items):
    """``NEURALBOKEH_TEST_ORDER=reverse`` runs the test files in reverse order (``.ci/run``'s
    second pass): a test that passes only after another file ran, or only with a thread
    count some earlier test left behind, fails there."""
    if os.environ.get("NEURALBOKEH_TEST_ORDER") == "reverse":
        files = list(dict.fromkeys(item.fspath for item in items))
        rank = {f: i for i, f in enumerate(reversed(files))}
        items.sort(key=lambda item: rank[item.fspath])  # stable: the order within a file is kept


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    """A 5-scene, 3-slice, 40x32 synthetic dataset made by the real CLI (7-blade aperture, cat-eye)."""
    from data_tools.synth import main

    out = tmp_path_factory.mktemp("data") / "tiny"
    rc = main(["--out", str(out), "--scenes", "5", "--size", "40", "32", "--slices", "3",
               "--aperture", "polygon:7", "--cat-eye", "0.5", "--seed", "7"])
    assert rc == 0
    return out


def _train_tiny(tiny_dataset, tmp_path_factory, architecture: str) -> Path:
    from neuralbokeh.training import load_config, train

    root = tmp_path_factory.mktemp("run")
    cfg_path = root / "cfg.toml"
    cfg_path.write_text(f"""
[data]
roots = ["{tiny_dataset}"]
test_fraction = 0.2
[model]
architecture = "{architecture}"
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
def trained_checkpoint(tiny_dataset, tmp_path_factory) -> Path:
    """The default (lens) network trained by ``train()`` for a few steps on ``tiny_dataset`` (6 tiles of 16 px)."""
    return _train_tiny(tiny_dataset, tmp_path_factory, "lens")


@pytest.fixture(scope="session")
def trained_paper_checkpoint(tiny_dataset, tmp_path_factory) -> Path:
    """The same with the paper's network."""
    return _train_tiny(tiny_dataset, tmp_path_factory, "paper")


def busy(path: Path, out: Path, seed: int = 11) -> Path:
    """A checkpoint made far from the identity it starts as, with seeded random weights (parity and
    stability need a busy network): the paper's C2 and every second convolution; the lens
    network's pupils (log-transmission noise: lopsided, grainy kernels), cat-eye and channel scales."""
    import torch

    from neuralbokeh.checkpoint import load_checkpoint, save_checkpoint

    data = load_checkpoint(path)
    g = torch.Generator().manual_seed(seed)
    state = dict(data["model_state"])
    for name, t in state.items():
        if name.startswith("c2.") or ".conv_b." in name:
            state[name] = 0.3 * torch.randn(t.shape, generator=g, dtype=t.dtype) / max(1, t[0].numel()) ** 0.5
        elif name == "pupil_field":
            state[name] = t + 1.5 * torch.randn(t.shape, generator=g, dtype=t.dtype)
        elif name == "log_channel_scale":
            state[name] = torch.tensor([0.05, 0.0, -0.08], dtype=t.dtype)
        elif name == "vignette":  # a cat-eye: the pupils' centroid drifts over the field
            state[name] = t + torch.tensor([0.4, 0.3, 0.0], dtype=t.dtype)
    data["model_state"] = state
    save_checkpoint(out, {k: v for k, v in data.items() if k not in ("format", "format_version", "package_version")})
    return out


@pytest.fixture(scope="session")
def busy_checkpoint(trained_checkpoint, tmp_path_factory) -> Path:
    """``trained_checkpoint`` (lens network) made busy."""
    return busy(trained_checkpoint, tmp_path_factory.mktemp("busy") / "busy.pt")


@pytest.fixture(scope="session")
def busy_paper_checkpoint(trained_paper_checkpoint, tmp_path_factory) -> Path:
    """``trained_paper_checkpoint`` made busy."""
    return busy(trained_paper_checkpoint, tmp_path_factory.mktemp("busy") / "busy_paper.pt")


@pytest.fixture(scope="session")
def busy_onnx(busy_checkpoint, tmp_path_factory) -> Path:
    """``busy_checkpoint`` exported to ONNX with direct kernels."""
    from neuralbokeh.export.exporter import export_checkpoint

    path = tmp_path_factory.mktemp("onnx") / "busy.onnx"
    export_checkpoint(busy_checkpoint, path, kernels="direct", threads=1)
    return path


@pytest.fixture(scope="session")
def busy_paper_onnx(busy_paper_checkpoint, tmp_path_factory) -> Path:
    """``busy_paper_checkpoint`` exported to ONNX with direct kernels."""
    from neuralbokeh.export.exporter import export_checkpoint

    path = tmp_path_factory.mktemp("onnx") / "busy_paper.onnx"
    export_checkpoint(busy_paper_checkpoint, path, kernels="direct", threads=1)
    return path
