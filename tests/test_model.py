import pytest
import torch

from neuralbokeh.core.contract import Contract
from neuralbokeh.core.normalization import Normalization
from neuralbokeh.networks.config import ModelConfig
from neuralbokeh.networks.paper import PaperBokeh, PerChannelConv, tile, untile


def _paper(h, w, **kw):
    return PaperBokeh(ModelConfig(architecture="paper", **kw), Contract(h, w, Normalization(), 1.0, 1.0))


def _x(b, h, w, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, 4, h, w, generator=g) * 1.96 - 0.98


@pytest.mark.parametrize(
    "h, w, t, t_o, tiling",
    [(96, 128, 48, 12, "overlap"), (100, 77, 32, 16, "overlap"), (40, 32, 16, 4, "overlap"),
     (96, 128, 48, 12, "no_overlap"), (37, 50, 48, 12, "none"), (20, 20, 64, 32, "overlap")],
)
def test_tiling_round_trip_is_exact(h, w, t, t_o, tiling):
    layout = ModelConfig(blocks=1, tile=t, overlap=t_o, tiling=tiling, architecture="paper").layout(h, w)
    x = _x(2, h, w)
    tiles = tile(x, layout)
    rows, cols, core, ov = layout
    assert tiles.shape == (2, rows * cols * 4, core + 2 * ov, core + 2 * ov)
    assert torch.equal(untile(tiles, layout, h, w), x)


def test_layouts():
    assert ModelConfig(blocks=1, architecture="paper").layout(1080, 1920) == (6, 10, 200, 60)  # the paper's 200 + 60 px
    assert ModelConfig(blocks=1, tiling="no_overlap", architecture="paper").layout(1080, 1920) == (6, 10, 200, 0)
    assert ModelConfig(blocks=1, tiling="none", architecture="paper").layout(1080, 1920) == (1, 1, 1920, 0)
    assert ModelConfig(blocks=1, architecture="paper").layout(1080, 1920).num_tiles == 60


@pytest.mark.parametrize("h, w", [(96, 128), (50, 70)])
def test_untrained_network_is_exactly_the_identity(h, w):
    model = _paper(h, w, blocks=5, features=6, tile=32, overlap=8)
    x = _x(2, h, w)
    x[0, :3, 0, 0] = -1.0  # the very ends of the range too
    x[0, :3, 0, 1] = 0.999999
    assert torch.equal(model(x), x[:, :3])
    paper = _paper(h, w, blocks=5, features=6, tile=32, overlap=8, head="paper")
    assert not torch.allclose(paper(x), x[:, :3], atol=1e-2)


def test_shapes_kernels_and_parameters():
    model = _paper(40, 32, blocks=4, features=5, tile=16, overlap=4)
    assert [b.conv_a.kernel_size for b in model.blocks] == [3, 5, 7, 9]
    fixed = _paper(40, 32, blocks=4, features=5, tile=16, overlap=4, kernel_sizes="fixed3")
    assert [b.conv_a.kernel_size for b in fixed.blocks] == [3, 3, 3, 3]
    assert model(_x(3, 40, 32)).shape == (3, 3, 40, 32)
    assert model(_x(1, 40, 32), return_tiles=True).shape == (1, model.layout.num_tiles * 3, 24, 24)
    assert len(_paper(40, 32, blocks=0, tile=16, overlap=4).blocks) == 0
    with pytest.raises(ValueError, match=r"input must have shape \(B, 4, 40, 32\)"):
        model(_x(1, 32, 40))


def test_every_tile_has_its_own_weights():
    model = _paper(64, 64, blocks=2, features=4, tile=32, overlap=0, tiling="no_overlap")
    torch.nn.init.normal_(model.c2.weight)
    out = model(_x(1, 64, 64))
    out[..., :32, :32].sum().backward()  # only the top-left tile's output
    grads = model.c2.weight.grad.view(model.layout.num_tiles, 3, -1).abs().sum(dim=(1, 2))
    assert grads[0] > 0 and (grads[1:] == 0).all()


@pytest.mark.parametrize("k", [5, 15, 31])
def test_fft_convolution_equals_direct_with_gradients(k):
    torch.manual_seed(0)
    direct = PerChannelConv(6, k, fft_min_kernel=999, fft_min_kernel_train=999)
    fast = PerChannelConv(6, k, fft_min_kernel=1, fft_min_kernel_train=1)
    fast.load_state_dict(direct.state_dict())
    x1 = (torch.rand(2, 6, 40, 37) * 2 - 1).requires_grad_()
    x2 = x1.detach().clone().requires_grad_()
    y1, y2 = direct(x1), fast(x2)
    assert (y1 - y2).abs().max() < 1e-4
    w = torch.rand_like(y1)
    (y1 * w).sum().backward()
    (y2 * w).sum().backward()
    assert (x1.grad - x2.grad).abs().max() < 1e-4
    assert (direct.conv.weight.grad - fast.conv.weight.grad).abs().max() / direct.conv.weight.grad.abs().max() < 1e-4
    assert (direct.conv.bias.grad - fast.conv.bias.grad).abs().max() < 1e-3


def test_fft_switch_depends_on_gradients():
    conv = PerChannelConv(2, 7, fft_min_kernel=15, fft_min_kernel_train=5)
    assert conv.use_fft()
    with torch.no_grad():
        assert not conv.use_fft()


def test_config_validation():
    with pytest.raises(ValueError, match="overlap"):
        ModelConfig(blocks=1, tile=32, overlap=17, architecture="paper")
    with pytest.raises(ValueError, match="tiling must be one of"):
        ModelConfig(blocks=1, tiling="grid", architecture="paper")
    with pytest.raises(ValueError, match="blocks"):
        ModelConfig(blocks=-1, architecture="paper")
    with pytest.raises(ValueError, match="unknown model config keys"):
        ModelConfig.from_dict({**ModelConfig(blocks=1, architecture="paper").to_dict(), "depth": 3})
    cfg = ModelConfig(blocks=3, architecture="paper")
    assert ModelConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="resolved"):
        _paper(64, 64)  # blocks = "auto" must be resolved from the data first
    # a model config of a checkpoint written before the data contract is refused, not upgraded
    old = {"image_height": 64, "image_width": 64, "blocks": 2, "kernels": "fixed3", "architecture": "paper"}
    with pytest.raises(ValueError, match=r"unknown model config keys \['image_height', 'image_width', 'kernels'\]"):
        ModelConfig.from_dict(old)
