import os

import numpy as np
import pytest

from neuralbokeh.core.io import read_image, read_json, write_image, write_json


def test_exr_round_trip_is_exact_with_hdr_and_inf(tmp_path):
    g = np.random.default_rng(0)
    img = (g.random((7, 9, 3)) * 1e4).astype(np.float32)
    img[0, 0] = [np.inf, 0.0, 1e-30]
    path = write_image(tmp_path / "a.exr", img, channel_names=["R", "G", "B"], attributes={"neuralbokeh:units": "m"})
    back, attrs = read_image(path, with_attributes=True)
    assert back.dtype == np.float32 and back.shape == (7, 9, 3)
    assert np.array_equal(back, img)
    assert attrs["neuralbokeh:units"] == "m"
    depth = write_image(tmp_path / "d.exr", img[..., 0], channel_names=["Z"])
    assert read_image(depth).shape == (7, 9, 1)


def test_png_and_tiff(tmp_path):
    img = np.arange(12, dtype=np.uint8).reshape(2, 2, 3) * 20
    back = read_image(write_image(tmp_path / "a.png", img, pixel_type="uint8"))
    np.testing.assert_allclose(back, img / 255.0, atol=1e-6)
    f = np.full((3, 4, 3), 0.25, dtype=np.float32)
    assert np.array_equal(read_image(write_image(tmp_path / "a.tif", f)), f)


def test_write_is_atomic_and_leaves_no_temp_files(tmp_path, monkeypatch):
    target = tmp_path / "a.exr"
    write_image(target, np.ones((2, 2, 3)))
    before = target.read_bytes()

    class FailsHalfway:  # starts writing the file, then fails (a full disk, say)
        @staticmethod
        def create(name):
            return FailsHalfway()

        def open(self, name, spec):
            with open(name, "wb") as f:
                f.write(b"partial")
            return True

        def write_image(self, arr):
            return False

        def geterror(self):
            return "disk full"

        def close(self):
            pass

    monkeypatch.setattr("neuralbokeh.core.io.oiio.ImageOutput", FailsHalfway)
    with pytest.raises(OSError, match="cannot write .*a.exr: disk full"):
        write_image(target, np.zeros((2, 2, 3)))
    assert target.read_bytes() == before  # the old file is untouched
    assert sorted(os.listdir(tmp_path)) == ["a.exr"]  # no temporary file left behind


def test_written_files_get_normal_permissions(tmp_path):
    mask = os.umask(0o022)
    try:
        p = write_image(tmp_path / "a.exr", np.ones((2, 2, 3)))
        j = write_json(tmp_path / "a.json", {"x": 1})
    finally:
        os.umask(mask)
    assert p.stat().st_mode & 0o777 == 0o644 and j.stat().st_mode & 0o777 == 0o644


def test_bad_input_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such image"):
        read_image(tmp_path / "missing.exr")
    (tmp_path / "junk.exr").write_bytes(b"not an image")
    with pytest.raises(OSError, match="cannot read"):
        read_image(tmp_path / "junk.exr")
    with pytest.raises(ValueError, match="shape"):
        write_image(tmp_path / "x.exr", np.ones((2, 2, 2, 2)))
    with pytest.raises(ValueError, match=r"uint8 image values must be in \[0, 255\]"):
        write_image(tmp_path / "x.png", np.full((2, 2, 3), 300.0), pixel_type="uint8")
    with pytest.raises(OSError, match="cannot write"):
        write_image(tmp_path / "x.unknownext", np.ones((2, 2, 3)))
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ValueError, match="not valid JSON"):
        read_json(tmp_path / "bad.json")


def test_json_round_trip(tmp_path):
    data = {"a": [1, 2.5, None], "b": {"c": "d"}}
    assert read_json(write_json(tmp_path / "x.json", data)) == data


@pytest.mark.shared_data
def test_reads_real_focal_stack_png(shared_data):
    path = shared_data / "focal_stacks" / "breakfast_dfd" / "breakfast_near.png"
    img = read_image(path)
    assert img.shape[:2] == (480, 640) and img.shape[2] in (1, 3, 4)
    assert img.dtype == np.float32 and 0.0 <= img.min() and img.max() <= 1.0 and img.std() > 0.01


def test_data_windows_round_trip_and_place(tmp_path):
    from neuralbokeh.core.io import image_windows, place

    img = np.arange(2 * 3 * 1, dtype=np.float32).reshape(2, 3, 1)
    write_image(tmp_path / "w.exr", img, windows=((-1, 4, 3, 2), (0, 0, 8, 6)))
    assert image_windows(tmp_path / "w.exr") == ((-1, 4, 3, 2), (0, 0, 8, 6))
    np.testing.assert_array_equal(read_image(tmp_path / "w.exr"), img)
    got = place(img, (-1, 4, 3, 2), (0, 3, 4, 2), fill=-5.0)  # one column cut, one row and two columns empty
    np.testing.assert_array_equal(got[:, :, 0], [[-5, -5, -5, -5], [1, 2, -5, -5]])
    assert (place(img, (-1, 4, 3, 2), (10, 10, 2, 2), fill=7.0) == 7.0).all()  # no overlap at all
    with pytest.raises(ValueError, match="data window"):
        write_image(tmp_path / "bad.exr", img, windows=((0, 0, 4, 2), (0, 0, 8, 6)))


@pytest.mark.parametrize("name, tile", [("scan.exr", None), ("tiled.exr", 32), ("tiled.tif", 16)])
def test_a_region_reads_as_the_same_pixels_from_scanline_and_tiled_files(tmp_path, name, tile):
    """Rows x cols of a file read alone equal the whole image cut there, at tile-unaligned edges
    and at the image's last, partial tile."""
    import OpenImageIO as oiio

    img = np.random.default_rng(1).random((97, 150, 3)).astype(np.float32) * 100
    path = write_image(tmp_path / name, img, tile=tile)
    assert oiio.ImageInput.open(str(path)).spec().tile_width == (tile or 0)
    for rows, cols in [((33, 90), (17, 141)), ((64, 97), (128, 150)), ((0, 1), (149, 150)), (None, (5, 6))]:
        want = img[slice(*rows) if rows else slice(None), slice(*cols)]
        assert np.array_equal(read_image(path, rows=rows, cols=cols), want), (rows, cols)
    with pytest.raises(ValueError, match=r"cols \(140, 151\) are outside .*150x97 px"):
        read_image(path, rows=(0, 5), cols=(140, 151))
    with pytest.raises(ValueError, match="tile must be a multiple of 16 px for an .exr or .tif file, got 20"):
        write_image(tmp_path / "x.exr", img, tile=20)
    with pytest.raises(ValueError, match="got 32 for x.png"):
        write_image(tmp_path / "x.png", img, tile=32)
