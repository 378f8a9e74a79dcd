"""`raywave psfmap` and `raywave render`: files written, their contents, and one-line errors."""

import json

import imageio.v3 as iio
import numpy as np
import pytest

from raywave.cli.main import main

FAST = ["--ks", "16", "--rays", "16"]
# small crops keep the tests fast; the crop-energy warning is tested on its own
pytestmark = pytest.mark.filterwarnings("ignore::raywave.imaging.psfmap.PSFCropWarning")


@pytest.fixture(scope="module")
def rgb_map(tmp_path_factory):
    """A 2×2 RGB map of the bundled hybrid lens (default channel wavelengths), written by the CLI."""
    d = tmp_path_factory.mktemp("map")
    assert main(["psfmap", "hybrid_asphere", "--grid", "2", "2", *FAST, "-o", str(d / "map.npz"), "--png",
                 str(d / "map.png"), "--json"]) == 0
    return d


def test_psfmap_writes_the_map_and_its_mosaic(rgb_map, capsys):
    z = np.load(rgb_map / "map.npz")
    assert z["psf"].shape == (1, 3, 2, 2, 16, 16) and z["centers"].shape == (1, 3, 2, 2, 2)
    assert np.allclose(z["psf"].sum((-1, -2)), 1.0)
    assert z["wavelengths"].tolist() == [0.66, 0.53, 0.47] and np.isinf(z["depths"][0])
    assert z["sensor_size"].tolist() == [5.76, 3.24] and z["pitch"] == pytest.approx(0.003)
    # green (the lens's primary wavelength) lands on the nodes: (±0.5·2.88, ±0.5·1.62) mm
    assert np.allclose(z["centers"][0, 1], z["positions"] * [2.88, 1.62], atol=1e-9)
    assert (rgb_map / "map.png").stat().st_size > 5_000


def test_psfmap_several_depths_text_output(tmp_path, capsys):
    assert main(["psfmap", "hybrid_asphere", "--grid", "1", "2", "--depths", "inf", "400", "--wavelengths", "0.53",
                 *FAST, "-o", str(tmp_path / "m.npz"), "--png", str(tmp_path / "m.png")]) == 0
    out = capsys.readouterr().out
    assert "1×2 nodes" in out and "wrote" in out
    z = np.load(tmp_path / "m.npz")
    assert z["psf"].shape == (2, 1, 1, 2, 16, 16) and z["depths"].tolist()[1] == 400.0
    assert (tmp_path / "m_d0.png").exists() and (tmp_path / "m_d1.png").exists()


def test_psfmap_lens_without_a_doe_gets_a_blank_one_holding_every_node(tmp_path, capsys):
    assert main(["psfmap", "asphere_hk51", "--grid", "1", "2", "--wavelengths", "0.53", "--ks", "8", "--rays", "16",
                 "--doe-pitch", "0.002", "-o", str(tmp_path / "m.npz"), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["grid"] == [1, 2]
    # the default DOE holds the beams of the corner nodes of a 3×3 map, not only the lens file's fields
    from raywave.cli.imaging_commands import load_lens_for_map
    from raywave.assembly.build import beam_half_extent
    from raywave.lens.build import bundled_lens_path

    a = {"path": bundled_lens_path("asphere_hk51"), "doe_pitch": 0.002, "doe_size": None, "doe_distance": None,
         "sensor_pitch": None, "oversample": None, "mapping": "chief_ray", "doe_levels": None,
         "doe_wavelength": None, "doe_material": None}
    hl, fields = load_lens_for_map(a, (3, 3), None, [0.53])
    ext = beam_half_extent(hl.lens, hl.doe_z(), fields.reshape(-1, 2), [0.53])
    assert 0.5 * min(hl.doe.size) >= max(ext)


def write_picture(path, h=36, w=64):
    y, x = np.mgrid[0:h, 0:w]
    img = np.stack([(x * 4) % 256, (y * 7) % 256, ((x + y) * 3) % 256], -1).astype(np.uint8)
    img[10:14, 20:40] = 255
    iio.imwrite(path, img)
    return img


def test_render_from_a_saved_map_and_directly(rgb_map, tmp_path, capsys):
    src = write_picture(tmp_path / "in.png")
    assert main(["render", "hybrid_asphere", str(tmp_path / "in.png"), "--map", str(rgb_map / "map.npz"), "-o",
                 str(tmp_path / "out.png"), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    out = iio.imread(tmp_path / "out.png")
    assert out.shape == src.shape and out.dtype == np.uint8
    assert s["image_size"] == [64, 36] and s["image_pitch_mm"] == pytest.approx([0.09, 0.09])
    # 90 µm image pixels: the PSFs shrink to about one pixel, so the picture barely changes
    assert np.abs(out.astype(float) - src).mean() < 12
    assert main(["render", "hybrid_asphere", str(tmp_path / "in.png"), "--grid", "1", "1", *FAST, "--noise",
                 "--seed", "3", "-o", str(tmp_path / "out16.tif"), "--save-map", str(tmp_path / "m.npz")]) == 0
    assert iio.imread(tmp_path / "out16.tif").dtype == np.uint16
    assert np.load(tmp_path / "m.npz")["psf"].shape == (1, 3, 1, 1, 16, 16)


@pytest.mark.parametrize("argv,expected", [
    (["psfmap", "hybrid_asphere", "--grid", "1", "2", "3"], "--grid"),
    (["psfmap", "hybrid_asphere", "--grid", "0"], "--grid"),
    (["psfmap", "hybrid_asphere", "-o", "m.npy"], ".npz"),
    (["psfmap", "hybrid_asphere", "--wavelengths", "550"], "µm"),
    (["psfmap", "hybrid_asphere", "--depths", "-5"], "--depths"),
    (["psfmap", "no_such_lens"], "not found"),
    (["render", "hybrid_asphere", "IMG"], "-o"),
    (["render", "hybrid_asphere", "missing.png", "-o", "o.png"], "not found"),
    (["render", "hybrid_asphere", "IMG", "-o", "o.txt"], "-o"),
    (["render", "hybrid_asphere", "IMG", "-o", "o.png", "--wavelengths", "0.6", "0.5"], "three"),
    (["render", "hybrid_asphere", "IMG", "-o", "o.png", "--depth", "0"], "--depth"),
    (["psfmap", "hybrid_asphere", "--device", "tpu"], "--device"),
    (["render", "hybrid_asphere", "IMG", "-o", "o.png", "--device", "gpu0"], "--device"),
])
def test_bad_input_is_one_line(argv, expected, tmp_path, capsys):
    write_picture(tmp_path / "in.png")
    argv = [str(tmp_path / "in.png") if a == "IMG" else a for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("raywave: error:") and expected in err and err.count("\n") == 1


def test_render_map_depth_mismatch_is_an_error(rgb_map, tmp_path, capsys):
    write_picture(tmp_path / "in.png")
    assert main(["render", "hybrid_asphere", str(tmp_path / "in.png"), "--map", str(rgb_map / "map.npz"), "--depth",
                 "300", "-o", str(tmp_path / "o.png")]) == 2
    assert "depths" in capsys.readouterr().err


def test_render_with_the_three_wavelength_average(tmp_path, capsys):
    write_picture(tmp_path / "in.png", 27, 48)
    assert main(["render", "hybrid_asphere", str(tmp_path / "in.png"), "--grid", "1", "1", "--ks", "8", "--rays",
                 "16", "--average", "-o", str(tmp_path / "o.png"), "--json", "--save-map", str(tmp_path / "m.npz")]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["average"] and s["wavelengths_um"] == [0.66, 0.53, 0.47]
    assert np.load(tmp_path / "m.npz")["psf"].shape == (1, 3, 1, 1, 8, 8)  # the channel-averaged map


def test_device_option_on_this_machine(tmp_path, capsys):
    """``--device cpu`` gives the default's map; a CUDA device this machine lacks is a one-line error naming it,
    and on a machine with CUDA the map computed there equals the CPU's (docs/architecture.md, Devices)."""
    import torch

    args = ["psfmap", "hybrid_asphere", "--grid", "1", "1", "--wavelengths", "0.53", *FAST]
    assert main([*args, "-o", str(tmp_path / "a.npz")]) == 0
    assert main([*args, "-o", str(tmp_path / "b.npz"), "--device", "cpu"]) == 0
    a, b = np.load(tmp_path / "a.npz"), np.load(tmp_path / "b.npz")
    assert np.array_equal(a["psf"], b["psf"])
    capsys.readouterr()
    if torch.cuda.is_available():
        assert main([*args, "-o", str(tmp_path / "c.npz"), "--device", "cuda"]) == 0
        c = np.load(tmp_path / "c.npz")
        assert np.abs(c["psf"] - a["psf"]).max() <= 1e-10 * a["psf"].max()
    else:
        assert main([*args, "--device", "cuda"]) == 2
        err = capsys.readouterr().err
        assert "--device" in err and "CUDA" in err and err.count("\n") == 1
