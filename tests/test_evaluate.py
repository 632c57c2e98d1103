"""Baselines, metrics and the evaluation report."""

import json

import numpy as np
import pytest
import torch

from neuralbokeh.core.apertures import ApertureModel, Polygon, ViewGrid
from neuralbokeh.evaluation.evaluate import BASELINES, main, model_labels
from neuralbokeh.evaluation.metrics import flip_hdr, image_metrics, paired_by_scene, pareto_front, tonemap_srgb
from neuralbokeh.render import scatter_defocus
from neuralbokeh.render.baselines import gather_defocus, gaussian_defocus, pseudo_ray_trace


def _point(coc_px: float, size: int = 48):
    x = torch.full((1, 3, size, size), 0.1, dtype=torch.float64)
    x[..., size // 2, size // 2 - 4] = 1000.0
    return x, torch.full((1, 1, size, size), coc_px, dtype=torch.float64)


def test_gather_equals_scatter_under_uniform_coc_and_keeps_flux():
    x, c = _point(9.0)
    ap = ApertureModel(Polygon(7))
    g = gather_defocus(x, c, ap)
    assert float((g - scatter_defocus(x, c, ap)).abs().max()) < 1e-9
    assert float(g.sum()) == pytest.approx(float(x.sum()), rel=1e-9)
    assert float(g.max()) < 1000.0 / 20  # the point is spread over the 9 px heptagon


def test_gaussian_point_light_is_round_and_keeps_flux():
    x, c = _point(9.0)
    out = gaussian_defocus(x, c)[0, 1].numpy() - 0.1
    assert out.sum() == pytest.approx(1000.0, rel=1e-3)
    cy, cx = 24, 20
    assert out[cy, cx + 3] == pytest.approx(out[cy + 3, cx], rel=1e-6)  # isotropic
    assert out[cy, cx] > out[cy, cx + 3] > 0
    # 6 px from the centre is outside the 9 px CoC (radius 4.5): no light, up to FFT round-off
    assert abs(out[cy, cx + 6]) < 1e-9 * out.sum()


def test_step_edge_at_a_depth_discontinuity():
    size = 48
    x = torch.full((1, 3, size, size), 0.2, dtype=torch.float64)
    x[..., : size // 2] = 5.0  # a bright in-focus foreground on the left
    c = torch.full((1, 1, size, size), 9.0, dtype=torch.float64)
    c[..., : size // 2] = 0.0
    ap = ApertureModel(Polygon(7))
    g, s = gather_defocus(x, c, ap), scatter_defocus(x, c, ap)
    assert torch.allclose(g[..., : size // 2], x[..., : size // 2], atol=1e-9)  # CoC 0 gathers only itself
    # naive gather: the blurred background next to the edge gathers the sharp foreground (leak)
    assert float(g[0, 0, 20, size // 2 + 1]) > 1.0 and float(g[0, 0, 20, size // 2 + 1]) > float(s[0, 0, 20, size // 2 + 1])
    gs = gaussian_defocus(x, c)
    assert torch.allclose(gs[..., : size // 2 - 1], x[..., : size // 2 - 1], atol=1e-9)  # sharp foreground stays sharp


def test_pseudo_ray_tracing_point_light_and_step_edge():
    ap = ApertureModel(Polygon(7))
    x, c = _point(9.0)
    r = pseudo_ray_trace(x, c, ap)
    assert float(r.sum()) == pytest.approx(float(x.sum()), rel=1e-12)  # every ray finds the point once
    lit = (r[0, 0] - 0.1) > 1.0
    s = scatter_defocus(x, c, ap)[0, 0] - 0.1
    assert 0.7 * int((s > 1.0).sum()) <= int(lit.sum()) <= int((s > 1.0).sum())  # the heptagon, one ray per pixel
    size = 48
    x = torch.full((1, 3, size, size), 0.2, dtype=torch.float64)
    x[..., : size // 2] = 5.0
    c = torch.full((1, 1, size, size), 9.0, dtype=torch.float64)
    c[..., : size // 2] = 0.0
    r, g = pseudo_ray_trace(x, c, ap), gather_defocus(x, c, ap)
    assert torch.equal(r[..., : size // 2], x[..., : size // 2])  # in focus: every ray hits the pixel itself
    assert torch.allclose(r[..., size // 2 :], x[..., size // 2 :])  # depth-aware: no foreground leaks behind
    assert float(g[0, 0, 20, size // 2 + 1]) > 1.0  # where the naive gather leaks
    yang = pseudo_ray_trace(x, c, ap, blending="yang")
    assert torch.isfinite(yang).all()
    with pytest.raises(ValueError, match="blending must be"):
        pseudo_ray_trace(x, c, ap, blending="gamma")


def test_metrics_against_hand_values():
    ref = np.zeros((16, 20, 3))
    ref[0, 0, 0] = 1.0  # peak 1
    m = image_metrics(ref + 0.1, ref)
    assert m["psnr_linear"] == pytest.approx(20.0, abs=1e-4)  # MSE 0.01 at peak 1
    assert tonemap_srgb(np.array([1.0]))[0] == pytest.approx(0.7353569, abs=1e-6)  # sRGB(0.5), Reinhard(1) = 0.5
    same = image_metrics(ref + 0.3, ref + 0.3)
    assert same["ssim_linear"] == pytest.approx(1.0) and same["ssim_srgb"] == pytest.approx(1.0)
    assert same["flip_hdr"] == 0.0 and flip_hdr(ref + 0.3, ref + 0.6) > 0.0
    with pytest.raises(ValueError, match="must be finite and >= 0"):
        image_metrics(ref - 1.0, ref)
    assert pareto_front([(1.0, 5.0), (2.0, 3.0), (3.0, 4.0), (10.0, 1.0)]) == [0, 1, 3]


def test_methods_are_compared_scene_by_scene():
    def per(values):  # two slices per scene
        return [{"sample": f"scene_{i // 2:03d}#{i % 2}", "psnr_linear": v, "flip_hdr": -v / 100} for i, v in enumerate(values)]

    # scene means: a = 11, 20, 30; b = 10, 22, 30 -> differences +1, -2, 0
    a, b = per([10.0, 12.0, 20.0, 20.0, 29.0, 31.0]), per([10.0, 10.0, 22.0, 22.0, 30.0, 30.0])
    psnr = paired_by_scene(a, b, "psnr_linear")
    assert psnr["scenes"] == 3 and psnr["ahead"] == 1
    assert psnr["median"] == pytest.approx(0.0) and psnr["mean"] == pytest.approx(-1 / 3)
    assert -2.0 <= psnr["ci95"][0] < -1 / 3 < psnr["ci95"][1] <= 1.0  # a resampled mean stays within the differences
    flip = paired_by_scene(a, b, "flip_hdr")  # lower is better: a's larger PSNR is a lower FLIP here
    assert flip["ahead"] == 1 and flip["mean"] == pytest.approx(1 / 300)
    with pytest.raises(ValueError, match="different scenes"):
        paired_by_scene(a, b[:4], "psnr_linear")
    with pytest.raises(ValueError, match="unknown metric 'psnr'"):
        paired_by_scene(a, b, "psnr")


def test_report_files_and_identity_row(tiny_dataset, busy_onnx, tmp_path):
    rc = main(["--data", str(tiny_dataset), "--models", str(busy_onnx), "--baselines", "all",
               "--out", str(tmp_path / "report"), "--repeats", "1", "--threads", "1", "--samples", "2"])
    assert rc == 0
    for name in ("report.json", "report.md", "error_vs_runtime.png", "grid_median.png", "grid_worst.png"):
        assert (tmp_path / "report" / name).is_file(), name
    report = json.loads((tmp_path / "report" / "report.json").read_text())
    assert list(report["methods"]) == ["busy.onnx", *BASELINES]
    from neuralbokeh.data.dataset import FocalStackDataset

    ds = FocalStackDataset(tiny_dataset, "test", 0.2, 0, normalize=False)
    it = ds[0]
    want = image_metrics(it["aif"].numpy().transpose(1, 2, 0).astype(np.float64),
                         it["defocus"].numpy().transpose(1, 2, 0).astype(np.float64))
    got = report["methods"]["identity"]["per_sample"][0]
    assert got["psnr_srgb"] == pytest.approx(want["psnr_srgb"]) and got["flip_hdr"] == pytest.approx(want["flip_hdr"])
    assert all(m["ms_per_mp"] > 0 for m in report["methods"].values())
    md = (tmp_path / "report" / "report.md").read_text()
    assert "| gather |" in md and "busy.onnx against each method, scene by scene" in md
    by_scene = report["by_scene"]["methods"]["identity"]["psnr_srgb"]
    assert by_scene["scenes"] == 1 and by_scene["mean"] == pytest.approx(  # both samples are one scene's slices
        report["methods"]["busy.onnx"]["psnr_srgb"] - report["methods"]["identity"]["psnr_srgb"])
    with pytest.raises(SystemExit, match="unknown baselines"):
        main(["--data", str(tiny_dataset), "--baselines", "bogus", "--out", str(tmp_path / "r2")])


def test_split_all_and_the_default_split_follows_the_training_run(tiny_dataset, busy_checkpoint, busy_onnx, tmp_path):
    from neuralbokeh.checkpoint import load_checkpoint, save_checkpoint
    from neuralbokeh.evaluation.evaluate import load_model_method, split_of_models

    rc = main(["--data", str(tiny_dataset), "--baselines", "identity", "--split", "all", "--out", str(tmp_path / "all"),
               "--repeats", "1", "--threads", "1"])
    assert rc == 0
    report = json.loads((tmp_path / "all" / "report.json").read_text())
    assert report["info"]["split"] == "all" and report["info"]["samples"] == 5 * 3  # every scene, every slice
    # the split is the training run's unless given: from a checkpoint and from its export
    data = load_checkpoint(busy_checkpoint)
    data["train_config"]["data"].update(test_fraction=0.4, split_seed=7)
    other = save_checkpoint(tmp_path / "other.pt",
                            {k: v for k, v in data.items() if k not in ("format", "format_version", "package_version")})
    loaded = load_model_method(other, 1)
    assert split_of_models([loaded], None, None) == (0.4, 7)
    assert split_of_models([loaded], 0.2, None) == (0.2, 7)  # a given value wins (with a warning)
    trained = load_checkpoint(busy_checkpoint)["train_config"]["data"]
    assert split_of_models([load_model_method(busy_onnx, 1)], None, None) == (trained["test_fraction"], trained["split_seed"])
    assert split_of_models([], None, None) == (0.2, 0)


def test_the_pupil_picture_shows_the_learned_pupil_beside_the_declared_aperture(trained_checkpoint, trained_paper_checkpoint,
                                                                                 tiny_dataset, tmp_path):
    """``python -m neuralbokeh.evaluation.pupils``: a network that starts from the data's aperture
    (``pupil_init = "aperture"``, no cat-eye) shows, at the sensor's centre, exactly the
    reference panel; a learned cat-eye clips the corner's pupil on the side away from the
    centre; the CLI writes the sheet and refuses what it cannot show."""
    from neuralbokeh.core.apertures.spec import parse_aperture
    from neuralbokeh.core.contract import Contract
    from neuralbokeh.core.io import read_image
    from neuralbokeh.core.normalization import Normalization
    from neuralbokeh.evaluation.pupils import learned_pupils, pupil_distance, reference_panel
    from neuralbokeh.evaluation.pupils import main as pupils_main
    from neuralbokeh.networks import ModelConfig, build_model

    shape = Polygon(7)
    contract = Contract(32, 32, Normalization(), 9.0, 9.0, aperture=ApertureModel(shape).to_dict())
    model = build_model(ModelConfig(tile=16, overlap=4, pupil_init="aperture", vignetting=False).resolved(9.0), contract)
    centre = learned_pupils(model, [(0.0, 0.0)])[0]
    np.testing.assert_allclose(centre, reference_panel(shape, model.config.pupil_size), atol=1.01e-3)  # the 1e-3 floor
    ref = reference_panel(shape, model.config.pupil_size)
    assert pupil_distance(centre, ref) < 0.01  # only the floor outside the polygon
    assert pupil_distance(3.0 * ref, ref) == pytest.approx(0.0)  # brightness is not shape
    left, right = ref * (np.arange(ref.shape[1]) < 24)[:, None], ref * (np.arange(ref.shape[1]) >= 24)[:, None]
    assert pupil_distance(left, right) == pytest.approx(1.0)  # halves that share no sample
    disk = reference_panel(parse_aperture("disk"), model.config.pupil_size)
    assert 0.10 < pupil_distance(disk, ref) < 0.15  # a 7-gon in its circle: 1 - 7 sin(2 pi / 7) / (2 pi) = 0.129 outside
    views = reference_panel(ViewGrid(np.ones((3, 3))), 48)[..., 0]  # a light field's views: 9 points, not 9 cells
    assert (views > 0).sum() == 9 and views.sum() == pytest.approx(9.0)
    cat = build_model(ModelConfig(tile=16, overlap=4, pupil_init="aperture").resolved(9.0), contract)
    with torch.no_grad():
        cat.vignette.copy_(torch.tensor([0.6, 0.6, 0.0]))  # a unit circle moving 0.6 radii per unit of field
    corner = learned_pupils(cat, [(1.0, -1.0)])[0, ..., 1]  # the top-right corner: x right, y up
    p = cat.config.pupil_size
    top_right, bottom_left = corner[: p // 3, -p // 3 :].sum(), corner[-p // 3 :, : p // 3].sum()
    assert top_right < 0.2 * bottom_left, (top_right, bottom_left)

    out = tmp_path / "pupils.png"
    assert pupils_main([str(trained_checkpoint), "--out", str(out), "--scene", str(next(tiny_dataset.glob("scene_*")))]) == 0
    size = model.config.pupil_size * 4
    assert read_image(out).shape == (size, 4 * size + 3 * 4, 3)  # the reference, then centre, edge, corner
    with pytest.raises(FileExistsError, match="--overwrite"):
        pupils_main([str(trained_checkpoint), "--out", str(out)])
    with pytest.raises(ValueError, match="only the lens network learns pupils"):
        pupils_main([str(trained_paper_checkpoint), "--out", str(tmp_path / "paper.png")])


def test_models_that_share_a_file_name_get_rows_of_their_own(tmp_path):
    # two runs' checkpoint.pt once shared one row: the second's scores replaced the first's
    a, b, c = tmp_path / "a" / "run" / "checkpoint.pt", tmp_path / "b" / "run" / "checkpoint.pt", tmp_path / "m.onnx"
    assert model_labels([a, b, c]) == ["a/run/checkpoint.pt", "b/run/checkpoint.pt", "m.onnx"]
    assert model_labels([c]) == ["m.onnx"]
    with pytest.raises(ValueError, match="names one file twice"):
        model_labels([c, tmp_path / "." / "m.onnx"])
