"""Mitsuba 3 focal stacks: depth conversion, aperture equivalence, CoC match, orientation,
sharding/resume and the cross-check against our scatter renderer, on tiny scenes."""

import json
import math

import numpy as np
import pytest
import torch

pytest.importorskip("mitsuba", reason="mitsuba is not installed (pip install mitsuba)")

from data_tools.mitsuba.__main__ import main, parse_shard, shard_indices  # noqa: E402
from data_tools.mitsuba.render import mitsuba_defocus, planar_depth_from_aov, render_aif, render_depth, tangent_grid  # noqa: E402
from data_tools.mitsuba.scenes import Camera, fov_for_lens  # noqa: E402
from data_tools.mitsuba.variant import activate, llvm_candidates, probe  # noqa: E402
from neuralbokeh.core.apertures import ApertureModel, Disk, MaskAperture, Polygon
from neuralbokeh.core.optics import ThinLens
from neuralbokeh.data.dataset import FocalStackDataset
from neuralbokeh.evaluation.metrics import image_metrics
from neuralbokeh.render import render_defocus as scatter_render


@pytest.fixture(scope="module")
def mi():
    return activate("scalar_rgb")  # the tests pin the portable variant; the probe is tested below


def _camera(mi, width, height, focal_mm=50.0, sensor_mm=36.0):
    look = mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, 1, 0])
    return Camera(np.array(look.matrix, dtype=np.float64).reshape(4, 4), fov_for_lens(focal_mm, sensor_mm), width, height)


def _rect(mi, z, half, albedo, tilt_deg=0.0, x=0.0, texture=None):
    T = mi.ScalarTransform4f
    bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": albedo}}
    if texture is not None:
        bsdf = {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(texture), "raw": True}}
    to_world = T().translate([x, 0.0, z]).rotate([0, 1, 0], 180.0 + tilt_deg).scale([half, half, 1.0])
    return {"type": "rectangle", "bsdf": bsdf, "to_world": to_world}


def _point_scene(mi, camera, depth_m, x_tan=0.0, y_tan=0.0, radius_px=0.2):
    r = depth_m * camera.tan_half_x * 2.0 / camera.width * radius_px
    return mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 2},
                         "light": {"type": "sphere", "center": [-x_tan * depth_m, -y_tan * depth_m, depth_m], "radius": r,
                                   "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}}})


def test_variant_probe_runs_in_a_subprocess():
    assert probe("scalar_rgb")
    assert not probe("llvm_ad_rgb", "/nonexistent/libLLVM-99.so")  # a bad library fails there, not here
    assert llvm_candidates()[-1] is None


def test_planar_depth_of_a_tilted_plane(mi):
    cam = _camera(mi, 40, 30)
    theta = math.radians(35.0)
    scene = mi.load_dict({"type": "scene", "plane": _rect(mi, 2.0, 0.8, [0.5, 0.5, 0.5], tilt_deg=35.0)})
    got = render_depth(mi, scene, cam)
    x, y = tangent_grid(cam)
    d = np.stack([-x, -y, np.ones_like(x)], axis=-1)  # image right is world -x, image down is world -y
    n = np.array([math.sin(theta), 0.0, math.cos(theta)])
    z = 2.0 * n[2] / (d @ n)  # planar depth where the ray meets the plane through (0, 0, 2)
    hit_x = z * d[..., 0]
    on = np.abs(hit_x / math.cos(theta)) < 0.8 - 0.05  # well inside the rectangle's half-width
    assert on.sum() > 300 and np.abs(got[on] - z[on]).max() < 1e-4 * z[on].max()
    assert np.ptp(z[on]) > 0.5  # the plane really spans depths
    off = np.abs(hit_x / math.cos(theta)) > 0.8 + 0.05
    assert off.any() and np.isinf(got[off]).all()  # misses are +inf, never 0
    with np.errstate(divide="ignore"):
        assert np.isinf(planar_depth_from_aov(np.zeros((30, 40)), cam)).all()


def test_disk_accumulation_matches_the_thinlens_sensor(mi):
    cam = _camera(mi, 32, 32)
    rng = np.random.default_rng(0)
    tex = rng.uniform(0.1, 0.9, (16, 16, 3)).astype(np.float32)
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 2},
                          "env": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
                          "back": _rect(mi, 6.0, 4.0, None, texture=tex),
                          "front": _rect(mi, 1.0, 0.12, None, x=0.1, texture=tex[::-1].copy())})
    lens, ap = ThinLens(50.0, 1.4, 36.0), ApertureModel(Disk())
    a = mitsuba_defocus(mi, scene, cam, lens, ap, 2.0, 512, "thinlens", seed=1)
    b = mitsuba_defocus(mi, scene, cam, lens, ap, 2.0, 512, "accumulate", seed=2)
    assert a.spp == b.spp == 512
    psnr = image_metrics(b.image, a.image)["psnr_linear"]
    assert psnr >= 35.0, psnr
    sharp = render_aif(mi, scene, cam, 64)
    assert image_metrics(sharp, a.image)["psnr_linear"] < psnr - 3  # the blur is there to be matched


@pytest.mark.parametrize("method", ["thinlens", "accumulate"])
@pytest.mark.parametrize("depth, focus", [(2.0, 0.4), (0.3, 1.5)])  # behind, in front of the focus
def test_emissive_point_blur_diameter_matches_coc(mi, method, depth, focus):
    cam = _camera(mi, 64, 64)
    lens = ThinLens(50.0, 1.2, 36.0)
    want = lens.coc_px(depth, focus, cam.width)
    assert want > 8.0
    res = mitsuba_defocus(mi, _point_scene(mi, cam, depth), cam, lens, ApertureModel(Disk()), focus, 1024, method)
    img = res.image[..., 1]
    yy, xx = np.mgrid[:64, :64]
    m = img.sum()
    cy, cx = (img * yy).sum() / m, (img * xx).sum() / m
    r2 = (((yy - cy) ** 2 + (xx - cx) ** 2) * img).sum() / m
    # a uniform disk of diameter d has E[r^2] = d^2 / 8; pixel integration adds 1/12 per axis
    diameter = 2.0 * math.sqrt(2.0 * (r2 - 1.0 / 6.0))
    assert abs(diameter - want) < 1.0, (diameter, want)
    assert abs(cy - 31.5) < 0.5 and abs(cx - 31.5) < 0.5  # registered: the blur is centred on the pinhole image


def test_aperture_orientation_and_cat_eye_match_the_kernels(mi):
    cam = _camera(mi, 48, 48)
    lens = ThinLens(50.0, 1.2, 36.0)
    tri = ApertureModel(Polygon(3, rotation_deg=90.0), cat_eye=0.8)
    corr = {}
    for depth, focus in ((2.0, 0.3), (0.3, 2.0)):  # behind, then in front of the focus: CoC 9.4 and -8.1 px
        x_tan, y_tan = (41.5 / 24 - 1) * cam.tan_half_x, (9.5 / 24 - 1) * cam.tan_half_x  # pixel (9, 41): the cat-eye clips
        img = mitsuba_defocus(mi, _point_scene(mi, cam, depth, x_tan, y_tan, 0.5), cam, lens, tri, focus, 1024, seed=3).image[..., 1]
        col, row = 41.0, 9.0
        c = lens.coc_px(depth, focus, 48)
        half_diag = 0.5 * math.hypot(47, 47)
        k = tri.kernels(c, ((col - 23.5) / half_diag, (row - 23.5) / half_diag))[1]
        if depth < focus:
            k = k[::-1, ::-1]  # in front of the focus: point-reflected
        r = k.shape[0] // 2
        patch = img[round(row) - r : round(row) + r + 1, round(col) - r : round(col) + r + 1]
        plain = ApertureModel(tri.shape).kernels(c)[1]  # the same triangle without the cat-eye
        plain = plain[::-1, ::-1] if depth < focus else plain

        def cc(kernel):
            return float(np.corrcoef(patch.ravel(), kernel.ravel())[0, 1])

        corr[depth] = (cc(k), cc(k[::-1, ::-1]), cc(plain))
    for depth, (right, flipped, no_cat_eye) in corr.items():
        assert right > 0.85 and right > flipped + 0.1 and right > no_cat_eye, (depth, corr)


def test_cli_shards_resume_and_noise_target(mi, tmp_path):
    out = tmp_path / "ds"
    common = ["--out", str(out), "--scenes", "3", "--size", "24", "16", "--slices", "2", "--spp", "16", "--aif-spp", "4",
              "--aperture", "polygon:7", "--cat-eye", "0.6", "--variant", "scalar_rgb"]
    assert main([*common, "--shard", "0/2"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["scene_00000", "scene_00002"]
    before = (out / "scene_00000" / "defocus_0.exr").stat().st_mtime_ns
    assert main([*common, "--shard", "1/2"]) == 0
    assert main([*common, "--shard", "0/2"]) == 0  # a rerun skips the finished scenes
    assert (out / "scene_00000" / "defocus_0.exr").stat().st_mtime_ns == before
    ds = FocalStackDataset(out)
    assert len(ds.scenes) == 3 and len(ds) == 6
    meta = json.loads((out / "scene_00001" / "scene.json").read_text())
    assert [s["spp"] for s in meta["generator"]["slices"]] == [16, 16] and meta["generator"]["variant"] == "scalar_rgb"
    assert sorted(shard_indices(10, (0, 3)) + shard_indices(10, (1, 3)) + shard_indices(10, (2, 3))) == list(range(10))
    again = tmp_path / "again"
    assert main([*common[2:], "--out", str(again), "--only", "2", "0", "--spp", "32"]) == 0  # held-out scenes at more spp
    assert sorted(p.name for p in again.iterdir()) == ["scene_00000", "scene_00002"]
    a, b = (json.loads((d / "scene_00002" / "scene.json").read_text()) for d in (out, again))
    assert a["generator"]["scene"] == b["generator"]["scene"] and a["focus_distances_m"] == b["focus_distances_m"]
    assert b["generator"]["slices"][0]["spp"] == 32
    with pytest.raises(SystemExit, match="--only takes scene indices 0 .. 2"):
        main([*common[2:], "--out", str(again), "--only", "3"])
    noisy = tmp_path / "noisy"
    assert main(["--out", str(noisy), "--scenes", "1", "--size", "24", "16", "--slices", "1", "--spp", "64", "--aif-spp", "4",
                 "--noise-target", "1.0", "--variant", "scalar_rgb"]) == 0
    meta = json.loads((noisy / "scene_00000" / "scene.json").read_text())
    assert meta["generator"]["slices"][0]["spp"] == 32 and meta["generator"]["slices"][0]["rounds"] == 2  # stopped early
    with pytest.raises(ValueError, match="i/n"):
        parse_shard("2/2")
    with pytest.raises(SystemExit, match="thinlens"):
        main(["--out", str(tmp_path / "x"), "--aperture", "polygon:5", "--method", "thinlens", "--variant", "scalar_rgb"])


def test_fronto_parallel_scene_agrees_with_the_reference_scatter(mi):
    cam = _camera(mi, 64, 64, focal_mm=85.0)
    rng = np.random.default_rng(1)
    tex = [rng.uniform(0.1, 0.9, (8, 8, 3)).astype(np.float32) for _ in range(3)]
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 2},
                          "env": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
                          "back": _rect(mi, 8.0, 6.0, None, texture=tex[0]),
                          "mid": _rect(mi, 3.0, 0.5, None, x=-0.3, texture=tex[1]),
                          "front": _rect(mi, 1.5, 0.15, None, x=0.2, texture=tex[2])})
    lens, ap = ThinLens(85.0, 1.4, 36.0), ApertureModel(Polygon(7), cat_eye=0.6)
    aif, depth = render_aif(mi, scene, cam, 1024), render_depth(mi, scene, cam)  # noise-limited: 512 spp gave 35.1 dB
    ours = scatter_render(torch.from_numpy(aif.transpose(2, 0, 1))[None], torch.from_numpy(depth)[None, None], lens, 3.0, ap)
    theirs = mitsuba_defocus(mi, scene, cam, lens, ap, 3.0, 2048, seed=4).image
    assert lens.coc_px(np.array([1.5, 8.0]), 3.0, 64).min() > 1.5  # both planes off the focus are blurred
    psnr = image_metrics(ours[0].numpy().transpose(1, 2, 0), theirs)["psnr_linear"]
    assert psnr >= 35.0, psnr


def test_cli_renders_a_users_xml_scene_in_its_units(mi, tmp_path):
    xml = tmp_path / "user.xml"
    xml.write_text("""<scene version="3.0.0">
    <default name="res" value="16"/>
    <integrator type="path"><integer name="max_depth" value="2"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="0, 0, 0" target="0, 0, 1" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="$res"/></film>
    </sensor>
    <emitter type="constant"/>
    <shape type="rectangle">
        <transform name="to_world"><scale value="3000"/><rotate y="1" angle="180"/><translate z="2500"/></transform>
    </shape>
</scene>""")  # modelled in mm: a wall 2.5 m away
    out = tmp_path / "ds"
    assert main(["--out", str(out), "--scene-xml", str(xml), "--xml-param", "res=20", "--unit-m", "0.001", "--slices", "1",
                 "--focus", "1.0", "--spp", "8", "--aif-spp", "4", "--aperture", "polygon:6", "--variant", "scalar_rgb"]) == 0
    meta = json.loads((out / "scene_00000" / "scene.json").read_text())
    assert meta["image_size"] == {"width": 20, "height": 20}  # the file's film, its $res set from the command line
    assert meta["depth_range_m"][0] == pytest.approx(2.5, rel=1e-4)  # mm -> m
    assert meta["lens"]["sensor_width_mm"] == pytest.approx(2 * 50.0 * math.tan(math.radians(20.0)), rel=1e-5)
    with pytest.raises(SystemExit, match="NAME=VALUE"):
        main(["--out", str(out), "--scene-xml", str(xml), "--xml-param", "res", "--variant", "scalar_rgb"])


def test_a_square_aperture_renders_a_square(mi):
    # The one pupil definition (neuralbokeh.core.apertures.pupil_grid): an all-ones mask is the
    # whole pupil square, as in the kernels; Mitsuba's lens points used to be cut to a disk.
    cam = _camera(mi, 40, 40)
    lens = ThinLens(50.0, 1.2, 36.0)
    depth, focus = 2.0, 0.3
    img = mitsuba_defocus(mi, _point_scene(mi, cam, depth, 0.0, 0.0, 0.5), cam, lens,
                         ApertureModel(MaskAperture(np.ones((8, 8)))), focus, 1024, seed=4).image[..., 1]
    c = lens.coc_px(depth, focus, 40)
    yy, xx = np.mgrid[:40, :40]
    square = (np.abs(yy - 19.5) <= c / 2) & (np.abs(xx - 19.5) <= c / 2)
    lit = img > 0.25 * np.percentile(img[square], 90)
    iou = float((lit & square).sum() / (lit | square).sum())
    assert iou >= 0.9, iou


def test_a_rendered_light_field_becomes_a_dataset_scene(mi, tmp_path, capsys):
    """``--light-field 3``: views across the pupil and their disparity, which the light-field
    tool turns into a scene that the package's check accepts, the views' signs found."""
    from data_tools.lightfield import main as lightfield_main

    lf = tmp_path / "lf"
    assert main(["--out", str(lf), "--scenes", "1", "--planar", "--size", "64", "48", "--light-field", "3", "--spp", "16",
                 "--f-number", "0.5", "--variant", "scalar_rgb", "--seed", "2"]) == 0  # a wide array: clear parallax
    hint = capsys.readouterr().out.split("--disparity-to-depth 0 ")[1].split()[0]
    folder = lf / "lf_00000"
    assert sorted(p.name for p in folder.iterdir())[:2] == ["depth.exr", "disparity.exr"]
    assert len(list(folder.glob("view_*.exr"))) == 9
    meta = json.loads((folder / "lightfield.json").read_text())
    assert meta["disparity_to_depth"]["beta_px_m"] == pytest.approx(float(hint))
    args = [str(folder), "--pattern", "view_{:03d}.exr", "--disparity", str(folder / "disparity.exr"), "--transfer", "linear",
            "--disparity-to-depth", "0", hint, "--out", str(tmp_path / "ds"), "--slices", "2"]
    assert lightfield_main(args) == 0  # the signs found from the views
    out = capsys.readouterr().out
    assert "view signs   (-1, -1) (chosen" in out  # a point moves against the camera, as the CLI's hint says
    from neuralbokeh.data.check import check_scene

    assert check_scene(tmp_path / "ds" / "lf_00000") == []
    with pytest.raises(SystemExit, match="odd N >= 3"):
        main(["--out", str(tmp_path / "x"), "--light-field", "4", "--variant", "scalar_rgb"])
