"""Image data: folder loader, the offline sample pool and its fixed split, dead leaves (determinism and the
natural-image power spectrum), sRGB conversion."""

import subprocess
import sys
import warnings

import numpy as np
import pytest
import torch

from raywave.imaging import data
from raywave.imaging.data import (SAMPLE_PHOTOS, SAMPLE_SPLIT, DeadLeavesDataset, ImageFolderDataset,
                                  SamplePhotoDataset, dead_leaves, linear_to_srgb, load_sample_photo,
                                  random_crop_flip, read_image, sample_photo_paths, srgb_to_linear)


def radial_spectrum_slope(img: torch.Tensor, f_lo: float, f_hi: float) -> float:
    """Least-squares slope of log(power) vs log(radial frequency) of the grey image (Hann-windowed), over
    f_lo < |f| < f_hi cycles/pixel."""
    im = img.mean(0).double()
    im = im - im.mean()
    n = im.shape[-1]
    win = torch.hann_window(n, periodic=False, dtype=torch.float64)
    p = torch.fft.fft2(im * win[:, None] * win[None, :]).abs() ** 2
    f = torch.fft.fftfreq(n, dtype=torch.float64)
    fr = (f[:, None] ** 2 + f[None, :] ** 2).sqrt()
    sel = (fr > f_lo) & (fr < f_hi)
    a = torch.stack([fr[sel].log(), torch.ones_like(fr[sel])], 1)
    return float(torch.linalg.lstsq(a, p[sel].log()[:, None]).solution[0])


# ------------------------------------------------------------------ sRGB
def test_srgb_round_trip_and_reference_values():
    x = torch.linspace(0, 1, 1001, dtype=torch.float64)
    assert torch.allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-12)
    # IEC 61966-2-1: sRGB 0.5 ↔ linear 0.21404; the linear segment below 0.04045
    assert float(srgb_to_linear(torch.tensor(0.5, dtype=torch.float64))) == pytest.approx(0.214041, abs=1e-6)
    assert float(srgb_to_linear(torch.tensor(0.04, dtype=torch.float64))) == pytest.approx(0.04 / 12.92)


# ------------------------------------------------------------------ folder
@pytest.fixture
def folder(tmp_path):
    import imageio.v3 as iio

    rng = np.random.default_rng(0)
    for split, n in (("train", 3), ("valid", 2)):
        (tmp_path / split).mkdir()
        for i in range(n):
            iio.imwrite(tmp_path / split / f"{i:04d}.png", rng.integers(0, 256, (40 + i, 50, 3), dtype=np.uint8))
    iio.imwrite(tmp_path / "train" / "grey.jpg", rng.integers(0, 256, (48, 48), dtype=np.uint8))
    (tmp_path / "train" / "notes.txt").write_text("not an image")
    return tmp_path


def test_read_image_shapes_and_encoding(folder):
    import imageio.v3 as iio

    a = iio.imread(folder / "train" / "0000.png")
    x = read_image(folder / "train" / "0000.png", dtype=torch.float64)
    assert x.shape == (3, 40, 50)
    assert torch.equal(x, torch.from_numpy(a).permute(2, 0, 1).double() / 255)
    g = read_image(folder / "train" / "grey.jpg")
    assert g.shape == (3, 48, 48) and torch.equal(g[0], g[1])
    lin = read_image(folder / "train" / "0000.png", linear=True, dtype=torch.float64)
    assert torch.allclose(lin, srgb_to_linear(x))
    with pytest.raises(ValueError, match="notes.txt"):
        read_image(folder / "train" / "notes.txt")


def test_folder_dataset_splits_crops_flips_determinism(folder):
    ds = ImageFolderDataset(folder, "train", patch_size=32, patches_per_image=2, seed=3)
    assert len(ds) == 4 * 2 and [p.name for p in ds.files] == ["0000.png", "0001.png", "0002.png", "grey.jpg"]
    items = [ds[i] for i in range(len(ds))]
    for x in items:
        assert x.shape == (3, 32, 32) and x.dtype == torch.float32 and 0 <= float(x.min()) and float(x.max()) <= 1
    # order-independent determinism: same (seed, epoch, index) → same crop, other seeds/epochs differ
    again = ImageFolderDataset(folder, "train", patch_size=32, patches_per_image=2, seed=3)
    assert all(torch.equal(again[i], items[i]) for i in reversed(range(len(ds))))
    other = ImageFolderDataset(folder, "train", patch_size=32, patches_per_image=2, seed=4)
    assert not all(torch.equal(other[i], items[i]) for i in range(len(ds)))
    ds.set_epoch(1)
    assert not all(torch.equal(ds[i], items[i]) for i in range(len(ds)))
    # every crop is a (flipped) window of the linearised image
    full = srgb_to_linear(read_image(folder / "train" / "0000.png"))
    x = items[0]
    windows = full.unfold(1, 32, 1).unfold(2, 32, 1)  # (3, nr, nc, 32, 32)
    found = any(torch.allclose(windows[:, r, c], v) for r in range(windows.shape[1]) for c in range(windows.shape[2])
                for v in (x, x.flip(-1), x.flip(-2), x.flip(-1).flip(-2)))
    assert found
    valid = ImageFolderDataset(folder, "valid", patch_size=None, linear=False)
    assert [tuple(v.shape) for v in (valid[0], valid[1])] == [(3, 40, 50), (3, 41, 50)]


def test_folder_dataset_errors(folder, tmp_path):
    with pytest.raises(ValueError, match="split 'test'"):
        ImageFolderDataset(folder, "test")
    with pytest.raises(ValueError, match="larger than the image"):
        ImageFolderDataset(folder, "valid", patch_size=64)[0]
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no images"):
        ImageFolderDataset(tmp_path / "empty")
    with pytest.raises(ValueError, match="does not exist"):
        ImageFolderDataset(tmp_path / "nope")


def test_random_crop_flip_uses_only_its_generator():
    img = torch.arange(3 * 20 * 30, dtype=torch.float32).reshape(3, 20, 30)
    torch.manual_seed(0)
    a = random_crop_flip(img, (8, 12), torch.Generator().manual_seed(5))
    torch.manual_seed(1)  # the global RNG plays no part
    b = random_crop_flip(img, (8, 12), torch.Generator().manual_seed(5))
    assert torch.equal(a, b) and a.shape == (3, 8, 12)


# ------------------------------------------------------------------ offline sample pool
def test_sample_split_is_fixed_disjoint_and_covers_the_pool():
    train, ev = set(SAMPLE_SPLIT["train"]), set(SAMPLE_SPLIT["eval"])
    assert not train & ev
    assert train | ev == set(SAMPLE_PHOTOS)
    assert SAMPLE_SPLIT["eval"] == ("coffee", "motorcycle", "flower")  # fixed: held-out numbers stay comparable


def test_sample_photos_are_installed_and_read_offline():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # every photo of the pool ships with the declared dependencies
        paths = sample_photo_paths("all")
    assert list(paths) == list(SAMPLE_SPLIT["train"] + SAMPLE_SPLIT["eval"])
    x = load_sample_photo("coffee")
    assert x.shape == (3, 400, 600) and 0 <= float(x.min()) and float(x.max()) <= 1
    with pytest.raises(ValueError, match="unknown sample photo 'lena'"):
        load_sample_photo("lena")


def test_missing_sample_photo_is_skipped_or_raised_never_downloaded(monkeypatch):
    monkeypatch.setitem(SAMPLE_PHOTOS, "coffee", ("skimage", "data/not_shipped.png"))
    with pytest.warns(data.MissingSampleWarning, match="coffee"):
        paths = sample_photo_paths("eval")
    assert "coffee" not in paths and len(paths) == 2
    with pytest.raises(FileNotFoundError, match="not_shipped"):
        sample_photo_paths("eval", missing="raise")


def test_sample_pool_does_not_import_matplotlib_or_fetchers():
    code = ("import sys; from raywave.imaging.data import SamplePhotoDataset; d = SamplePhotoDataset('all', 32);"
            "d[0]; bad = [m for m in ('matplotlib', 'pooch', 'sklearn', 'skimage.data') if m in sys.modules];"
            "assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_sample_dataset_shapes_ranges_determinism():
    ds = SamplePhotoDataset("eval", patch_size=64, patches_per_image=2, seed=1)
    assert ds.names == ["coffee", "motorcycle", "flower"] and len(ds) == 6
    xs = [ds[i] for i in range(len(ds))]
    assert all(x.shape == (3, 64, 64) and 0 <= float(x.min()) and float(x.max()) <= 1 for x in xs)
    ds2 = SamplePhotoDataset("eval", patch_size=64, patches_per_image=2, seed=1)
    assert all(torch.equal(ds2[i], xs[i]) for i in range(len(ds)))


# ------------------------------------------------------------------ dead leaves
def test_dead_leaves_shape_range_determinism():
    a = dead_leaves((48, 64), torch.Generator().manual_seed(7))
    b = dead_leaves((48, 64), torch.Generator().manual_seed(7))
    c = dead_leaves((48, 64), torch.Generator().manual_seed(8))
    assert a.shape == (3, 48, 64) and a.dtype == torch.float32
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert 0 <= float(a.min()) and float(a.max()) <= 1
    ds = DeadLeavesDataset(32, length=4, seed=2)
    assert torch.equal(ds[3], DeadLeavesDataset(32, length=4, seed=2)[3])
    with pytest.raises(ValueError, match="r_min"):
        dead_leaves(16, torch.Generator(), r_min=0)


def test_dead_leaves_power_spectrum_slope_is_about_minus_two():
    """Scale-invariant dead leaves (radii ∝ r^-3) have a radial power spectrum ∝ f^-2 (natural images: −2 ± 0.3
    typically). Measured over 4 images of 192² px between 4/192 and 0.25 cycles/pixel: about −2.1 to −2.3."""
    slopes = [radial_spectrum_slope(dead_leaves(192, torch.Generator().manual_seed(i)), 4 / 192, 0.25)
              for i in range(4)]
    mean = sum(slopes) / len(slopes)
    assert -2.5 < mean < -1.8, slopes
    # control: white noise is flat, so the fit is not biased toward −2
    noise = torch.rand(3, 192, 192, generator=torch.Generator().manual_seed(0))
    assert abs(radial_spectrum_slope(noise, 4 / 192, 0.25)) < 0.3


def test_dead_leaves_cover_the_image_and_occlude():
    """Every pixel belongs to some disc (no grey background left) and the colours are per-disc constants:
    without anti-aliasing, the number of distinct colours is far below the number of pixels."""
    x = dead_leaves(64, torch.Generator().manual_seed(0), supersample=1, r_min=2.0)
    flat = x.reshape(3, -1).T
    assert not bool((flat == 0.5).all(1).any())
    n_colours = len(torch.unique(flat, dim=0))
    assert 1 < n_colours < 64 * 64 / 4
