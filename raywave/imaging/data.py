"""Image data for end-to-end training: a user folder of photos, an offline pool of sample photos shipped inside
installed packages, and a procedural dead-leaves generator.

Every source yields float tensors ``(3, H, W)`` in [0, 1].

**Encoding.** Photo files are sRGB-encoded (gamma ≈ 2.2). Blur and noise act on *linear* irradiance, so the
datasets return linear intensities by default (``linear=True``: the sRGB decoding of IEC 61966-2-1 is
applied, :func:`srgb_to_linear`); :func:`linear_to_srgb` encodes a linear image back for display or for
writing a PNG. Dead leaves are generated directly in linear intensity.

**Randomness.** Nothing here touches torch's global RNG: crops and flips of item ``i`` at epoch ``e`` come
from a ``torch.Generator`` seeded with a hash of ``(seed, e, i)``, so an item is the same whatever the order
in which it is requested, in any DataLoader worker; the dead-leaves generator takes an explicit generator.

**Offline sample pool.** :data:`SAMPLE_PHOTOS` lists photos bundled in scikit-image, scikit-learn and
matplotlib. They are read directly from the installed package folders by file name (never through
``skimage.data`` functions, which may download through pooch): a missing file is reported and skipped, and
nothing is ever fetched from the network. skimage's ``motorcycle`` is the left view of its stereo pair
(``motorcycle_left.png``, shipped with scikit-image 0.26); where an installation lacks a file, the pool
simply has one photo fewer (a :class:`MissingSampleWarning` names it). The split is fixed
(:data:`SAMPLE_SPLIT`): 8 training photos, 3 held-out evaluation photos.
"""

from __future__ import annotations

import hashlib
import importlib.util
import math
import warnings
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

# one implementation of the sRGB curves (IEC 61966-2-1), shared with the sensor's display path
from raywave.imaging.sensor import linear_to_srgb, srgb_to_linear

__all__ = [
    "srgb_to_linear", "linear_to_srgb", "read_image", "random_crop_flip", "list_images", "ImageFolderDataset",
    "SAMPLE_PHOTOS", "SAMPLE_SPLIT", "sample_photo_paths", "load_sample_photo", "SamplePhotoDataset",
    "dead_leaves", "DeadLeavesDataset", "MissingSampleWarning", "IMAGE_EXTENSIONS",
]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


class MissingSampleWarning(UserWarning):
    """A sample photo of the offline pool is not installed (it is skipped, never downloaded)."""


# ------------------------------------------------------------------ files
def read_image(path, linear: bool = False, dtype=torch.float32) -> torch.Tensor:
    """An image file as ``(3, H, W)`` in [0, 1] (grey → 3 equal channels; alpha dropped; 8/16-bit scaled).

    ``linear=True`` decodes sRGB to linear intensity. Raises ``ValueError`` naming the file if it is not a
    readable 2-D grey/RGB(A) image."""
    import imageio.v3 as iio

    path = Path(path)
    if path.suffix.lower() not in IMAGE_EXTENSIONS:
        raise ValueError(f"{path}: not an image file (expected one of {', '.join(IMAGE_EXTENSIONS)})")
    try:
        a = np.asarray(iio.imread(path))
    except Exception as exc:  # imageio raises several types depending on the plugin
        raise ValueError(f"cannot read image {path}: {exc}") from exc
    return _to_tensor(a, path, linear, dtype)


def _to_tensor(a: np.ndarray, path, linear: bool, dtype) -> torch.Tensor:
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[-1] not in (1, 2, 3, 4):
        raise ValueError(f"{path}: expected a grey or RGB(A) image, got an array of shape {a.shape}")
    if a.shape[-1] in (2, 4):  # drop alpha
        a = a[..., :-1]
    if a.shape[-1] == 1:
        a = np.repeat(a, 3, axis=-1)
    if np.issubdtype(a.dtype, np.integer):
        scale = float(np.iinfo(a.dtype).max)
        x = torch.from_numpy(a.astype(np.float64) / scale)
    else:
        x = torch.from_numpy(a.astype(np.float64)).clamp(0.0, 1.0)
    x = x.permute(2, 0, 1).contiguous()
    if linear:
        x = srgb_to_linear(x)
    return x.to(dtype)


def list_images(folder) -> list[Path]:
    """Image files (``IMAGE_EXTENSIONS``, any case) directly inside ``folder``, sorted by name."""
    folder = Path(folder)
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)


# ------------------------------------------------------------------ crops and flips
def _item_generator(seed: int, epoch: int, index: int) -> torch.Generator:
    """A generator seeded from (seed, epoch, index) through a hash: items are independent of request order."""
    h = hashlib.blake2b(f"{int(seed)}/{int(epoch)}/{int(index)}".encode(), digest_size=8).digest()
    g = torch.Generator()
    g.manual_seed(int.from_bytes(h, "little") & ((1 << 63) - 1))
    return g


def random_crop_flip(img: torch.Tensor, size, generator: torch.Generator, flips: bool = True) -> torch.Tensor:
    """A random ``size`` = (h, w) (or int) crop of ``img (C, H, W)``, flipped left-right and up-down with
    probability 1/2 each (``flips``). Images smaller than the crop are an error naming both sizes."""
    h, w = (size, size) if isinstance(size, int) else (int(size[0]), int(size[1]))
    H, W = img.shape[-2:]
    if h > H or w > W:
        raise ValueError(f"crop {h}×{w} is larger than the image {H}×{W}")
    r = torch.randint(0, H - h + 1, (1,), generator=generator, device="cpu").item()
    c = torch.randint(0, W - w + 1, (1,), generator=generator, device="cpu").item()
    out = img[..., r:r + h, c:c + w]
    if flips:
        f = torch.rand(2, generator=generator, device="cpu")
        if f[0] < 0.5:
            out = out.flip(-1)
        if f[1] < 0.5:
            out = out.flip(-2)
    return out.contiguous()


class _PatchDataset(Dataset):
    """Base: ``len(images) × patches_per_image`` items; item ``i`` is a random crop of image ``i % n``."""

    def __init__(self, n_images: int, patch_size, patches_per_image: int, linear: bool, flips: bool, seed: int,
                 dtype):
        if n_images == 0:
            raise ValueError("no images")
        if int(patches_per_image) < 1:
            raise ValueError(f"patches_per_image must be >= 1, got {patches_per_image!r}")
        self.n_images = n_images
        self.patch_size = patch_size
        self.patches_per_image = int(patches_per_image)
        self.linear, self.flips, self.seed, self.dtype = bool(linear), bool(flips), int(seed), dtype
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        """Draw new crops for ``epoch`` (deterministic per (seed, epoch, index))."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return self.n_images * self.patches_per_image

    def _image(self, k: int) -> torch.Tensor:  # (3, H, W) sRGB-encoded, float
        raise NotImplementedError

    def __getitem__(self, index: int) -> torch.Tensor:
        if not -len(self) <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} items")
        index %= len(self)
        img = self._image(index % self.n_images)
        if self.patch_size is not None:
            img = random_crop_flip(img, self.patch_size, _item_generator(self.seed, self.epoch, index), self.flips)
        if self.linear:
            img = srgb_to_linear(img)
        return img.to(self.dtype)


class ImageFolderDataset(_PatchDataset):
    """Photos in a folder (DIV2K-style): ``root/*.png|jpg`` or, with ``split``, ``root/<split>/*``.

    Args:
        root: the folder. With ``split="train"``/``"valid"`` the images are taken from ``root/train`` /
            ``root/valid`` (DIV2K's ``DIV2K_train_HR``-style names are found too: any sub-folder whose name
            contains the split name, if exactly one does).
        patch_size: crop size (int or (h, w)); ``None`` returns whole images.
        patches_per_image: crops per image and epoch (the dataset length is images × this).
        linear: decode sRGB to linear intensity (default; see the module docstring).
        flips: random left-right / up-down flips.
        seed: crops of item i at epoch e are a function of (seed, e, i) only.
    Images are read from disk on each access (a DIV2K folder does not fit in memory as floats).
    """

    def __init__(self, root, split: str | None = None, patch_size=256, patches_per_image: int = 1,
                 linear: bool = True, flips: bool = True, seed: int = 0, dtype=torch.float32):
        root = Path(root)
        if not root.is_dir():
            raise ValueError(f"image folder {root} does not exist")
        folder = root if split is None else _split_folder(root, split)
        self.files = list_images(folder)
        if not self.files:
            raise ValueError(f"no images ({', '.join(IMAGE_EXTENSIONS)}) in {folder}")
        self.root = folder
        super().__init__(len(self.files), patch_size, patches_per_image, linear, flips, seed, dtype)

    def _image(self, k: int) -> torch.Tensor:
        return read_image(self.files[k], linear=False, dtype=torch.float32)


def _split_folder(root: Path, split: str) -> Path:
    exact = root / split
    if exact.is_dir():
        return exact
    cands = [p for p in sorted(root.iterdir()) if p.is_dir() and split.lower() in p.name.lower()]
    if len(cands) == 1:
        return cands[0]
    found = ", ".join(p.name for p in sorted(root.iterdir()) if p.is_dir()) or "none"
    raise ValueError(f"{root}: no unique sub-folder for split {split!r} (sub-folders: {found})")


# ------------------------------------------------------------------ offline sample photos
# name -> (package, path inside the installed package)
SAMPLE_PHOTOS: dict[str, tuple[str, str]] = {
    "astronaut": ("skimage", "data/astronaut.png"),
    "coffee": ("skimage", "data/coffee.png"),
    "chelsea": ("skimage", "data/chelsea.png"),
    "rocket": ("skimage", "data/rocket.jpg"),
    "hubble_deep_field": ("skimage", "data/hubble_deep_field.jpg"),
    "immunohistochemistry": ("skimage", "data/ihc.png"),
    "retina": ("skimage", "data/retina.jpg"),
    "motorcycle": ("skimage", "data/motorcycle_left.png"),
    "china": ("sklearn", "datasets/images/china.jpg"),
    "flower": ("sklearn", "datasets/images/flower.jpg"),
    "grace_hopper": ("matplotlib", "mpl-data/sample_data/grace_hopper.jpg"),
}

#: The fixed split of the pool: held-out photos are never used for training.
SAMPLE_SPLIT: dict[str, tuple[str, ...]] = {
    "train": ("astronaut", "chelsea", "rocket", "hubble_deep_field", "immunohistochemistry", "retina", "china",
              "grace_hopper"),
    "eval": ("coffee", "motorcycle", "flower"),
}


def _package_dir(package: str) -> Path | None:
    # find_spec locates the package without importing it (matplotlib must not be imported by physics code)
    spec = importlib.util.find_spec(package)
    if spec is None or spec.origin is None:
        return None
    return Path(spec.origin).parent


def sample_photo_paths(split: str = "train", missing: str = "warn") -> dict[str, Path]:
    """Installed files of the pool's ``split`` ("train", "eval" or "all"), in the split's fixed order.

    ``missing="warn"`` skips an absent photo with a :class:`MissingSampleWarning`; ``"raise"`` raises
    ``FileNotFoundError`` naming it. Nothing is downloaded."""
    if split == "all":
        names = SAMPLE_SPLIT["train"] + SAMPLE_SPLIT["eval"]
    elif split in SAMPLE_SPLIT:
        names = SAMPLE_SPLIT[split]
    else:
        raise ValueError(f"split must be 'train', 'eval' or 'all', got {split!r}")
    if missing not in ("warn", "raise"):
        raise ValueError(f"missing must be 'warn' or 'raise', got {missing!r}")
    out = {}
    for name in names:
        pkg, rel = SAMPLE_PHOTOS[name]
        base = _package_dir(pkg)
        path = None if base is None else base / rel
        if path is None or not path.is_file():
            msg = (f"sample photo {name!r} ({pkg}: {rel}) is not installed; it is skipped (raywave never "
                   "downloads data at run time)")
            if missing == "raise":
                raise FileNotFoundError(msg)
            warnings.warn(msg, MissingSampleWarning, stacklevel=2)
            continue
        out[name] = path
    return out


def load_sample_photo(name: str, linear: bool = False, dtype=torch.float32) -> torch.Tensor:
    """One photo of the pool by name as ``(3, H, W)`` in [0, 1] (sRGB-encoded unless ``linear``)."""
    if name not in SAMPLE_PHOTOS:
        raise ValueError(f"unknown sample photo {name!r}; known: {', '.join(SAMPLE_PHOTOS)}")
    split = "train" if name in SAMPLE_SPLIT["train"] else "eval"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MissingSampleWarning)
        paths = sample_photo_paths(split)
    if name not in paths:
        sample_photo_paths(split, missing="raise")  # raises naming the missing file
    return read_image(paths[name], linear=linear, dtype=dtype)


class SamplePhotoDataset(_PatchDataset):
    """Random crops of the offline sample pool's ``split`` ("train", "eval" or "all"); the photos are read
    once and kept as uint8-range float tensors (the pool is ~10 MB). Arguments as :class:`ImageFolderDataset`.
    """

    def __init__(self, split: str = "train", patch_size=128, patches_per_image: int = 8, linear: bool = True,
                 flips: bool = True, seed: int = 0, dtype=torch.float32):
        paths = sample_photo_paths(split)
        if not paths:
            raise ValueError(f"no photo of the sample pool's {split!r} split is installed")
        self.names = list(paths)
        self.images = [read_image(p, linear=False, dtype=torch.float32) for p in paths.values()]
        super().__init__(len(self.images), patch_size, patches_per_image, linear, flips, seed, dtype)

    def _image(self, k: int) -> torch.Tensor:
        return self.images[k]


# ------------------------------------------------------------------ dead leaves
def dead_leaves(size, generator: torch.Generator, r_min: float = 1.0, r_max: float | None = None,
                alpha: float = 3.0, channels: int = 3, supersample: int = 2, max_discs: int = 200_000,
                dtype=torch.float32, device=None) -> torch.Tensor:
    """A dead-leaves image ``(channels, h, w)`` in [0, 1] (linear intensity).

    Opaque discs fall one after another onto the image, each hiding whatever lies below; the first disc to
    cover a pixel decides its colour (equivalently: the image is seen from above). Radii follow the power law
    p(r) ∝ r^−alpha on [r_min, r_max] pixels; alpha = 3 makes the model scale invariant, with a radial power
    spectrum ∝ f^−2 like natural images (Lee, Mumford & Huang 2001). Centres are uniform over the image
    enlarged by r_max (no border bias); colours uniform in [0, 1]^channels. Discs are drawn until every pixel
    is covered (or ``max_discs``, then the rest keeps the mean grey 0.5).

    Args:
        size: int or (h, w) pixels.
        generator: the only source of randomness (a CPU ``torch.Generator``).
        r_min, r_max: radius range in pixels (default r_max = max(h, w) / 2).
        supersample: render on a grid this many times finer and average (anti-aliased disc edges).
    """
    h, w, r_max, s = _dead_leaves_args(size, r_min, r_max, alpha, supersample)
    H, W = h * s, w * s
    img = torch.full((channels, H, W), 0.5, dtype=torch.float64, device="cpu")
    filled = torch.zeros((H, W), dtype=torch.bool, device="cpu")
    remaining = H * W
    # pixel-centre coordinates in output pixels
    ys = (torch.arange(H, dtype=torch.float64, device="cpu") + 0.5) / s
    xs = (torch.arange(W, dtype=torch.float64, device="cpu") + 0.5) / s
    drawn = 0
    batch = 512
    while remaining > 0 and drawn < max_discs:
        r, cy, cx, col = _disc_batch(generator, batch, h, w, r_min, r_max, alpha, channels)
        for k in range(batch):
            remaining -= _drop_disc(img, filled, ys, xs, float(r[k]), float(cy[k]), float(cx[k]), col[k], s)
            if remaining == 0:
                break
        drawn += batch
    if s > 1:
        img = torch.nn.functional.avg_pool2d(img[None], s)[0]
    return img.to(dtype=dtype, device=device)


def _dead_leaves_args(size, r_min: float, r_max: float | None, alpha: float, supersample) -> tuple:
    """The checked arguments of :func:`dead_leaves`: ``(h, w, r_max, s)`` (pixels, pixels, radius in pixels with
    its default max(h, w) / 2, supersampling factor)."""
    h, w = (size, size) if isinstance(size, int) else (int(size[0]), int(size[1]))
    if h < 1 or w < 1:
        raise ValueError(f"size must be positive, got {size!r}")
    r_max = float(r_max) if r_max is not None else 0.5 * max(h, w)
    if not (0 < r_min <= r_max):
        raise ValueError(f"need 0 < r_min <= r_max, got r_min={r_min!r}, r_max={r_max!r}")
    if alpha <= 1:
        raise ValueError(f"alpha must be > 1, got {alpha!r}")
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample!r}")
    return h, w, r_max, s


def _disc_batch(generator: torch.Generator, batch: int, h: int, w: int, r_min: float, r_max: float, alpha: float,
                channels: int):
    """``batch`` random discs ``(r, cy, cx, colour)`` (pixels; float64), drawn from ``generator`` in this order:
    radii (power law r^-alpha on [r_min, r_max]), centre rows and columns (uniform over the image enlarged by
    r_max), colours (uniform in [0, 1]^channels)."""
    u = torch.rand(batch, generator=generator, dtype=torch.float64, device="cpu")
    # inverse CDF of p(r) ∝ r^-alpha on [r_min, r_max]
    a1 = 1.0 - alpha
    r = (r_min ** a1 + u * (r_max ** a1 - r_min ** a1)) ** (1.0 / a1)
    cy = -r_max + torch.rand(batch, generator=generator, dtype=torch.float64, device="cpu") * (h + 2 * r_max)
    cx = -r_max + torch.rand(batch, generator=generator, dtype=torch.float64, device="cpu") * (w + 2 * r_max)
    col = torch.rand(batch, channels, generator=generator, dtype=torch.float64, device="cpu")
    return r, cy, cx, col


def _drop_disc(img: torch.Tensor, filled: torch.Tensor, ys, xs, rk: float, yk: float, xk: float, colour,
               s: int) -> int:
    """Paint the disc of radius ``rk`` at (``yk``, ``xk``) (output pixels) with ``colour`` onto the supersampled
    ``img`` where no earlier disc lies (``filled``, updated); returns the number of newly covered samples."""
    H, W = filled.shape
    y0, y1 = max(int(math.floor((yk - rk) * s)), 0), min(int(math.ceil((yk + rk) * s)) + 1, H)
    x0, x1 = max(int(math.floor((xk - rk) * s)), 0), min(int(math.ceil((xk + rk) * s)) + 1, W)
    if y0 >= y1 or x0 >= x1:
        return 0
    inside = ((ys[y0:y1, None] - yk) ** 2 + (xs[None, x0:x1] - xk) ** 2) <= rk * rk
    new = inside & ~filled[y0:y1, x0:x1]
    n_new = int(new.sum())
    if n_new:
        img[:, y0:y1, x0:x1][:, new] = colour[:, None]
        filled[y0:y1, x0:x1] |= new
    return n_new


class DeadLeavesDataset(Dataset):
    """``length`` dead-leaves patches; item ``i`` at epoch ``e`` is a function of (seed, e, i) only.

    Keyword arguments other than ``size``/``length``/``seed`` go to :func:`dead_leaves`."""

    def __init__(self, size=128, length: int = 1000, seed: int = 0, **kw):
        if int(length) < 1:
            raise ValueError(f"length must be >= 1, got {length!r}")
        self.size, self.length, self.seed, self.kw = size, int(length), int(seed), kw
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> torch.Tensor:
        if not -self.length <= index < self.length:
            raise IndexError(f"index {index} out of range for {self.length} items")
        return dead_leaves(self.size, _item_generator(self.seed, self.epoch, index % self.length), **self.kw)
