"""End-to-end training of lens + DOE + reconstruction network (paper section 2.3, 2.5, 2.6).

Stages (each optional through its step count):

* **pre-stage**: optimise the PSFs directly: the mean RMS radius of the map's PSFs (aberration correction)
  plus ``similarity_weight`` × the mean L1 distance between the PSFs of different depths (EDoF), plus
  ``restore_weight`` × the worst depth's expected Wiener-restoration error (dB);
* **stage 1** (end-to-end): per iteration one wavelength per colour channel is drawn, the PSF map
  (``optics.grid`` × ``optics.depths``) is computed **without autograd**, training patches are rendered with the
  PSFs as leaf tensors at a random place on the sensor (at the sensor's pixel pitch), reconstructed by the
  network and compared with the sharp patches (L1/MSE, or the EDoF loss across depths); the loss is
  backpropagated to the network and to ∂L/∂PSF, then the map is **replayed** chunk by chunk with autograd
  (:class:`~raywave.training.replay.OpticsStep`) to get the lens/DOE gradients; no sensor noise;
* **stage 2** (fine-tuning): optics frozen, the ``optics.eval_grid`` map with all wavelengths averaged per
  channel (sensor-response weights), sensor noise (Poisson–Gaussian), only the network trains.

Everything random (wavelength draws, patch positions on the sensor, noise) comes from one ``torch.Generator``
(``seed``); the data order is a function of (seed, epoch). A checkpoint (every ``checkpoint_every`` steps and at
each stage's end) stores the modules, optimizer, scheduler, step and all random states, so a killed run resumes
bit-identically (:meth:`Trainer.run` resumes from the run folder's latest checkpoint).

Run folder: ``config.yaml`` (resolved), ``checkpoints/``, ``log.jsonl`` (loss per step), ``metrics.json``
(:meth:`Trainer.evaluate`), ``final/`` (lens JSON with its DOE phase, the DOE, fabrication masks).
The figures are written by the CLI (``raywave train``), which may import matplotlib; this module does not.
"""

from __future__ import annotations

import contextlib
import copy
import json
import math
import re
import shutil
import time
import warnings
from pathlib import Path

import torch

from raywave.training.checkpoint import checkpoint_path, latest_checkpoint, load_checkpoint, save_checkpoint
from raywave.training.config import TrainConfig, dump_config
from raywave.training.fabricating import FabricationSchedule
from raywave.training.losses import image_loss
from raywave.training.networks import DepthSelect, PSFAwareNet, build_network
from raywave.training.replay import OpticsStep, auto_chunk, chunk_ranges
from raywave.training.schedule import build_optimizer, param_groups, warmup_cosine_scheduler
from raywave.training.steps import _LIT_DRAWS, DarkRegionWarning, StageSteps, _lit_nodes, _nearest_node

__all__ = ["Trainer", "build_hybrid", "build_midsystem", "learned_doe", "STAGES", "CropWarning"]

STAGES = ("pre", "stage1", "stage2", "done")


class CropWarning(UserWarning):
    """A PSF window (``optics.ks`` / ``optics.eval_ks``) misses a noticeable part of a PSF's energy."""


#: an evaluation map of this many PSFs or more (the paper's 40×40 × 9 wavelengths: 14,400, ~1 CPU hour) keeps its
#: finished chunks in the run folder while it is computed (``eval_map_<model>``, removed once the map is whole): a run
#: resumed after an interruption computes only the rest
RESUMABLE_MAP_PSFS = 2000


def _resumable_map(folder, model, **kw):
    """``psf_map(model, **kw)`` with its chunks kept in ``folder`` (None: without) until the map is whole; a folder
    left by another map (the optics changed before the run was resumed) is replaced."""
    from raywave.imaging.psfmap import psf_map

    if folder is None:
        return psf_map(model, **kw)
    try:
        pm = psf_map(model, checkpoint=folder, **kw)
    except ValueError as e:
        if not str(e).startswith("checkpoint:"):
            raise
        shutil.rmtree(folder)
        pm = psf_map(model, checkpoint=folder, **kw)
    shutil.rmtree(folder, ignore_errors=True)
    return pm


def build_hybrid(lc):
    """The :class:`~raywave.hybrid.HybridLens` of a :class:`~raywave.training.config.LensConfig`: the lens file
    (bundled name or path), its DOE replaced by a zero-phase :func:`learned_doe` of the same grid (``doe: pixel`` /
    ``zernike``), refocused to ``focus_depth``, the refractive lens frozen unless ``train_lens``. A DOE inside the
    lens (``lens.doe_after``, or a lens file's surface DOE): :func:`build_midsystem`."""
    from raywave.assembly.build import load_hybrid
    from raywave.assembly.midsystem import surface_doe_positions
    from raywave.io import read_lens_spec
    from raywave.lens.build import resolve_lens_path

    path = resolve_lens_path(lc.file)
    if lc.doe_after is not None or surface_doe_positions(read_lens_spec(path)):
        return build_midsystem(lc, path)
    hl = load_hybrid(path, doe_pitch=lc.doe_pitch, doe_size=lc.doe_size, doe_distance=lc.doe_distance,
                     sensor_pitch=lc.sensor_pitch, stop_edge=lc.stop_edge, edge_step=lc.edge_step)
    if lc.sensor_size is not None:
        hl.lens.set_sensor(lc.sensor_size)
    if lc.focus_depth is not None:
        from raywave.lens.analysis import refocus

        refocus(hl.lens, float(lc.focus_depth))
    if lc.doe in ("pixel", "zernike"):
        doe = hl.doe
        hl = hl.with_doe(learned_doe(lc, doe.shape, doe.pitch, doe.aperture))
    elif lc.doe != "file":
        raise ValueError(f"lens.doe must be 'pixel', 'zernike' or 'file', got {lc.doe!r}")
    hl.lens.requires_grad_(bool(lc.train_lens))
    return hl


def learned_doe(lc, shape, pitch: float, aperture: str):
    """The zero-phase DOE to learn on the ``(ny, nx)`` grid of ``pitch`` mm: ``lens.doe: pixel``, a
    :class:`~raywave.doe.PixelDOE` (its memory checked first); ``zernike``, a :class:`~raywave.doe.ZernikeDOE` of
    ``lens.doe_terms`` coefficients over the grid's inscribed disk."""
    from raywave.doe import PixelDOE, ZernikeDOE

    if lc.doe == "zernike":
        return ZernikeDOE(torch.zeros(int(lc.doe_terms), dtype=torch.float64), tuple(shape), pitch, aperture=aperture)
    _check_pixel_doe_memory(shape, pitch, lc.file)
    return PixelDOE(torch.zeros(tuple(shape), dtype=torch.float64, device="cpu"), pitch, aperture=aperture)


#: a learned pixel DOE inside the lens without ``lens.doe_pitch``: this many pixels a side over its size
MIDSYSTEM_PIXELS = 256


def build_midsystem(lc, path):
    """The :class:`~raywave.hybrid.midsystem.MidSystemLens` of a :class:`~raywave.training.config.LensConfig` with a
    DOE inside the lens (issue 46): the lens file's own surface DOE, or (``lens.doe_after``) a DOE ``doe_distance``
    mm (default 0) after the vertex of surface ``doe_after`` (the file's DOE before the sensor, if any, left out),
    sized ``doe_size`` (default: the beams of the sensor's centre, edges and corners there), of pitch
    ``doe_pitch`` (default: the file's, else for a learned pixel DOE :data:`MIDSYSTEM_PIXELS` a side). The
    engine's plane near the sensor is the file's DOE plane when it had one (else
    :func:`raywave.assembly.midsystem.midsystem_of`'s choice). ``doe: pixel`` / ``zernike`` make the DOE a
    zero-phase :func:`learned_doe` of that grid. The sensor is set and refocused on the refractive lens; the
    refractive lens frozen unless ``train_lens``. ``lens.stop_edge`` / ``lens.edge_step``: the MidSystemLens's
    (None: its default, ``stop_edge="auto"``)."""
    from raywave.assembly.midsystem import doe_lens, midsystem_of, surface_doe_positions
    from raywave.io import read_lens_spec, validate_spec
    from raywave.io.errors import LensFileError

    spec = copy.deepcopy(read_lens_spec(path))
    size = None if lc.doe_size is None else [float(lc.doe_size)] * 2
    final = None  # the engine's plane near the sensor: midsystem_of's default
    if lc.doe_after is not None:
        if surface_doe_positions(spec):
            raise ValueError(f"lens.doe_after: {lc.file} already places a DOE at a surface; leave doe_after out")
        after = int(lc.doe_after)
        if not 0 <= after < len(spec["surfaces"]):
            raise ValueError(f"lens.doe_after: {after} is not a surface index of {lc.file} (0 .. "
                             f"{len(spec['surfaces']) - 1})")
        before = spec.pop("doe", None)  # the DOE before the sensor gives way to the one inside the lens ...
        if before is not None and before.get("distance") is not None:
            final = float(before["distance"])  # ... and its plane becomes the engine's (before any caustic)
        spec["surfaces"][after]["doe"] = {"distance": float(lc.doe_distance or 0.0), "phase": None}
        try:
            validate_spec(spec, str(path))
        except LensFileError as e:
            raise ValueError(f"lens.doe_after / doe_distance: {e}") from None
    plain = copy.deepcopy(spec)
    for s in plain["surfaces"]:
        s.pop("doe", None)
    fields = _sensor_fields(plain, lc, path)
    lens, doe, after, distance = doe_lens(spec, str(path), path.parent, lc.doe_pitch, size, fields)
    dspec = surface_doe_positions(spec)[0][2]
    sensor_pitch = lc.sensor_pitch if lc.sensor_pitch is not None else lens.pixel_pitch  # the file's pixel, as
    if lc.sensor_size is not None:  # build_hybrid keeps it when the sensor's size changes
        lens.set_sensor(lc.sensor_size)
    if lc.focus_depth is not None:
        from raywave.lens.analysis import refocus

        refocus(lens, float(lc.focus_depth))
    if lc.doe in ("pixel", "zernike"):
        own = lc.doe_pitch is not None or dspec.get("pitch") is not None or dspec.get("phase") is not None
        pitch = doe.pitch if own else max(doe.size) / MIDSYSTEM_PIXELS
        shape = doe.shape if own else tuple(max(1, round(s / pitch)) for s in (doe.size[1], doe.size[0]))
        doe = learned_doe(lc, shape, pitch, doe.aperture)
    elif lc.doe != "file":
        raise ValueError(f"lens.doe must be 'pixel', 'zernike' or 'file', got {lc.doe!r}")
    ml = midsystem_of(lens, doe, after, distance, final, sensor_pitch=sensor_pitch, fields=fields,
                      **({} if lc.stop_edge is None else {"stop_edge": lc.stop_edge}),
                      **({} if lc.edge_step is None else {"edge_step": lc.edge_step}))
    ml.lens.requires_grad_(bool(lc.train_lens))
    return ml


def _sensor_fields(spec: dict, lc, path) -> torch.Tensor:
    """(9, 2) field angles (deg) of the sensor's centre, edge midpoints and corners (``lens.sensor_size``, else
    the file's sensor or the square in its image circle), through the refractive lens of ``spec``: the beams a DOE
    inside the lens and the engine's plane must hold."""
    from raywave.imaging.psfmap import fields_at, sensor_size_of
    from raywave.lens.build import lens_from_spec

    lens = lens_from_spec(spec)
    if lc.sensor_size is not None:
        lens.set_sensor(lc.sensor_size)
    w, h = sensor_size_of(lens)
    pts = torch.tensor([[0.5 * w * i, 0.5 * h * j] for i in (-1, 0, 1) for j in (-1, 0, 1)], dtype=torch.float64)
    with torch.no_grad():
        return fields_at(lens, pts)


# bytes per DOE pixel while a pixel DOE trains: its float64 phase, gradient and Adam's two moments (32 B) and the
# replay backward's transient gradient of the phase window (~16 B: measured 4.7 GB for the Cooke triplet's 18063²)
PIXEL_DOE_TRAIN_BYTES = 48


def _check_pixel_doe_memory(shape, pitch: float, file) -> None:
    """Refuse, before anything is allocated, a pixel DOE whose training would not fit in memory (a lens file
    without a DOE gets one covering every field's beam at the Nyquist pitch, which for a large lens is 10⁸–10⁹
    pixels); the message names the lens and the settings that shrink it."""
    from raywave.utils.errors import check_allocation

    ny, nx = (int(v) for v in shape)
    check_allocation(float(ny) * float(nx) * PIXEL_DOE_TRAIN_BYTES,
                     f"training the {ny}×{nx} pixel DOE of {file} ({pitch * 1e3:g} µm pixels, "
                     f"{nx * pitch:g}×{ny * pitch:g} mm; phase, gradient and Adam's moments)",
                     "set lens.doe_size (a smaller DOE), lens.doe_pitch (coarser pixels, above the Nyquist pitch the "
                     "wavefront needs) or lens.doe_distance (a plane where the beams are smaller)", fraction=0.5)


def _kind(warning) -> str | None:
    """The once-per-run key of a warning whose wording varies with its sources (a DOEApertureWarning names one
    source, or "N sources of this call / map", differently each step): its kind and DOE size; None for the others
    (keyed by their message with the numbers masked)."""
    if getattr(warning, "entries", None) is not None and getattr(warning, "size", None) is not None:
        return f"DOE aperture {tuple(warning.size)}"
    if getattr(warning, "entries", None) is not None and type(warning).__name__ == "VignettingEdgeWarning":
        return "vignetting edge"
    return None


def _epoch_generator(seed: int, epoch: int) -> torch.Generator:
    g = torch.Generator()
    g.manual_seed((int(seed) * 7919 + int(epoch) * 104729 + 17) % (2 ** 62))
    return g


class Trainer(FabricationSchedule, StageSteps):
    """One training run (see the module docstring).

    Args:
        cfg: the configuration.
        run_dir: the run folder (created).
        hybrid: a ready :class:`~raywave.hybrid.HybridLens` instead of ``cfg.lens`` (tests, scripts).
        baseline: train the baseline: the DOE phase is set to zero and frozen, no pre-stage, the same network
            training (the "blank DOE" baseline of the aberration-correction application; ``cfg.baseline:
            paraxial``: the DOE designed with the paraxial wave model, :mod:`raywave.training.baselines`).
        progress: show tqdm progress bars.
        train_data, eval_data: datasets / image tensors instead of ``cfg.data`` (tests).
        field_cache: a :class:`~raywave.imaging.psfmap.DOEFieldCache` to share (e.g. the designed run's, for its
            baseline on the same frozen lens: the DOE-plane fields do not depend on the DOE's phase, and the
            cache empties itself if the optics differ); used only while the refractive lens is frozen.
    """

    def __init__(self, cfg: TrainConfig, run_dir, hybrid=None, baseline: bool = False, progress: bool = True,
                 train_data=None, eval_images=None, field_cache=None):
        from raywave.imaging.color import ColorSpec
        from raywave.imaging.psfmap import DOEFieldCache, field_grid, normalised_grid, sensor_size_of

        self.cfg, self.run_dir, self.baseline, self.progress = cfg, Path(run_dir), bool(baseline), progress
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.dtype = torch.float64 if cfg.dtype == "float64" else torch.float32
        self.device = torch.device(cfg.device)
        self.hl = (hybrid if hybrid is not None else build_hybrid(cfg.lens)).to(self.device)
        if self.baseline:
            with torch.no_grad():
                for p in self.hl.doe.parameters():
                    p.zero_()
            self.hl.doe.requires_grad_(False)
        self.train_lens = any(p.requires_grad for p in self.hl.lens.parameters())
        # a DOE inside the lens (MidSystemLens: no doe_fields) shapes the fields it propagates: nothing to cache
        cacheable = hasattr(self.hl, "doe_fields") and not self.train_lens
        self.cache = None if not cacheable else (DOEFieldCache() if field_cache is None else field_cache)
        wl = cfg.optics.wavelengths
        missing = [c for c in ("R", "G", "B") if c not in wl]
        if missing or set(wl) - {"R", "G", "B"}:
            raise ValueError(f"optics.wavelengths needs exactly the channels R, G, B, got {sorted(wl)}")
        self.color = ColorSpec([list(wl["R"]), list(wl["G"]), list(wl["B"])])
        self.depths = [float(d) for d in cfg.optics.depths]
        self.grid = tuple(int(v) for v in cfg.optics.grid)
        self.sensor_size = sensor_size_of(self.hl)
        with torch.no_grad():
            self.fields = field_grid(self.hl, self.grid, depth=self.depths[0]).reshape(-1, 2)
        self.positions = normalised_grid(self.grid, device=self.device)
        self.chunk = self._replay_chunk()
        self.pitch = self.hl.sensor_pitch
        self.train_data = train_data if train_data is not None else self._dataset("train")
        with torch.random.fork_rng(devices=[]):  # the initial weights depend on the seed only (global RNG untouched)
            torch.manual_seed(int(cfg.seed))
            self.net = self._build_net(cfg.network.deconv).to(self.device, self.dtype)
        self.gen = torch.Generator().manual_seed(int(cfg.seed))
        self.eval_images = eval_images
        self.loss_fn = image_loss(cfg.stage1.loss if cfg.stage1.loss != "edof" else "rmse")
        jit = float(cfg.optics.field_jitter)
        if not 0.0 <= jit <= 1.0:
            raise ValueError(f"optics.field_jitter must be in [0, 1] (a fraction of a grid cell), got {jit:g}")
        if cfg.pre_stage.about not in ("centroid", "center"):
            raise ValueError(f"pre_stage.about must be 'centroid' or 'center', got {cfg.pre_stage.about!r}")
        self.log_path = self.run_dir / "log.jsonl"
        self._seen_warnings: set = set()
        self.eval_ks = int(cfg.optics.eval_ks) if cfg.optics.eval_ks is not None else int(cfg.optics.ks)
        self._init_fabrication()
        self.stage2_map = None
        self._truth_map = None  # the lens's own evaluation map when the reconstruction uses another model's
        self.plain_net = None  # network.ablation: the plain network trained on the final optics
        self._frozen_maps: dict = {}
        dump_config(cfg, self.run_dir / "config.yaml")
        self.baseline_design = None
        if self.baseline:  # cfg.baseline "paraxial": design the (frozen) DOE with the paraxial model
            from raywave.training.baselines import prepare_baseline

            self.baseline_design = prepare_baseline(self)
        self.recon_model = self._recon_model()

    # ------------------------------------------------------------------ set-up helpers
    def _recon_model(self):
        """The model whose PSFs this run's reconstruction is built and trained with: the hybrid lens itself, or
        for a baseline with ``baseline_reconstruction: paraxial`` the paraxial model of it (the paper's
        baseline pipeline; its images are still simulated with the ray-wave model, :meth:`truth_map`)."""
        if self.baseline and self.cfg.baseline_reconstruction == "paraxial":
            from raywave.models import make_model

            return make_model("paraxial", self.hl)
        return self.hl

    def _map_kwargs(self, model) -> dict:
        """``cache`` and ``rays`` of a PSF-map call on ``model`` (the DOE-field cache and the ray count belong to
        the ray-wave model)."""
        if model is not self.hl:
            return {"cache": None}
        rays = self.cfg.optics.rays
        return {"cache": self.cache, **({"rays": rays} if rays else {})}

    def _build_net(self, deconv: str):
        """The reconstruction module: the network (``deconv: none``) or :class:`PSFAwareNet` (``wiener``; with
        ``wiener_select`` it deconvolves with each depth's map and picks per region by the image's evidence)."""
        if deconv == "none":
            return build_network(self.cfg.network.kind, **self._net_kwargs())
        if deconv not in ("wiener", "wiener_select"):
            raise ValueError(f"network.deconv must be 'wiener', 'wiener_select' or 'none', got {deconv!r}")
        from raywave.imaging.deconv import WienerDeconv

        select = None
        if deconv == "wiener_select":
            if len(self.depths) < 2:
                raise ValueError(f"network.deconv 'wiener_select' chooses between the depths' maps: it needs two or "
                                 f"more optics.depths, got {self.depths}; use 'wiener'")
            select = self._depth_select()
        n = self.cfg.network
        return PSFAwareNet(build_network(n.kind, **self._net_kwargs()),
                           WienerDeconv(3, init_lambda=n.wiener_lambda, init_mu=n.wiener_mu,
                                        init_chroma=n.wiener_chroma), select=select)

    def _depth_select(self):
        """:class:`DepthSelect` with the image prior measured on (up to 64 of) the training patches and the
        stage-2 sensor's noise."""
        from raywave.imaging.depth import power_spectrum_prior
        from raywave.imaging.sensor import Sensor

        n = min(len(self.train_data), 64)
        patches = torch.stack([torch.as_tensor(self.train_data[i]) for i in range(n)])
        s2 = self.cfg.stage2
        sensor = Sensor.from_electrons(full_well=s2.full_well, read_noise=s2.read_noise)
        return DepthSelect(power_spectrum_prior(patches), sensor.shot, sensor.read,
                           temperature=self.cfg.network.select_temperature)

    def reconstruct(self, sims, psf, cen, extents, positions=None, net=None) -> torch.Tensor:
        """The network's restoration of the simulated images ``sims (B, 3, h, w)`` at the normalised sensor
        ``extents`` (one per image). With ``network.deconv: wiener`` the images are first deconvolved
        (differentiably) with the PSF maps ``psf (D, 3, N, M, ks, ks)`` of the D depths (centres
        ``cen (D, 3, N, M, 2)``, averaged over the depths for the distortion): the camera does not know the
        object's distance, so one filter serves every depth, the one with the least expected error over the D
        maps (:mod:`raywave.imaging.deconv`; with D = 1 the Wiener filter of the map the images were rendered
        with). ``wiener_select`` deconvolves with each depth's map and blends by the depth weights of the
        image's evidence (:mod:`raywave.imaging.depth`)."""
        net = self.net if net is None else net
        if not isinstance(net, PSFAwareNet):
            return net(sims)
        return net(sims, psf, extents, **self._deconv_kwargs(cen, positions))

    def deconvolve(self, sims, psf, cen, extents, positions=None) -> torch.Tensor:
        """The deconvolution stage of :meth:`reconstruct` alone (``network.deconv`` wiener / wiener_select)."""
        return self.net.deconvolve(sims, psf, extents, **self._deconv_kwargs(cen, positions))

    def _deconv_kwargs(self, cen, positions=None) -> dict:
        return {"positions": self.positions if positions is None else positions, "centers": cen.mean(0),
                "depth_centers": cen, "sensor_size": self.sensor_size, "pitch": self.pitch}

    def _net_kwargs(self) -> dict:
        n = self.cfg.network
        if n.kind == "unet":
            return {"width": n.width, "depth": n.depth}
        return {"width": n.width, "enc_blocks": tuple(n.enc_blocks), "middle_blocks": n.middle_blocks}

    def _dataset(self, split: str):
        from raywave.imaging import data as D

        dc = self.cfg.data
        if dc.source == "samples":
            return D.SamplePhotoDataset(split, patch_size=dc.patch_size, patches_per_image=dc.patches_per_image,
                                        linear=dc.linear, seed=self.cfg.seed)
        if dc.source == "folder":
            if not dc.root:
                raise ValueError("data.source 'folder' needs data.root")
            return D.ImageFolderDataset(dc.root, "train" if split == "train" else "valid", patch_size=dc.patch_size,
                                        patches_per_image=dc.patches_per_image, linear=dc.linear, seed=self.cfg.seed)
        if dc.source == "dead_leaves":
            if split == "train":
                return D.DeadLeavesDataset(dc.patch_size, length=dc.dead_leaves_count, seed=self.cfg.seed)
            return D.SamplePhotoDataset("eval", patch_size=None, linear=dc.linear)
        raise ValueError(f"data.source must be 'samples', 'folder' or 'dead_leaves', got {dc.source!r}")

    def _stage_cfg(self, stage: str):
        return {"stage1": self.cfg.stage1, "stage2": self.cfg.stage2}[stage]

    def total_steps(self, stage: str) -> int:
        if stage == "pre":
            return 0 if self.baseline else int(self.cfg.pre_stage.steps)
        sc = self._stage_cfg(stage)
        per_epoch = max(len(self.train_data) // sc.batch_size, 1)
        n = sc.epochs * per_epoch
        return min(n, sc.max_steps) if sc.max_steps is not None else n

    def _optimizer(self, stage: str):
        if stage == "pre":
            pc = self.cfg.pre_stage
            groups = param_groups(self.hl.lens, self.hl.doe, None, lr_lens=pc.lr_lens, lr_doe=pc.lr_doe)
            total, warm, minr = self.total_steps("pre"), 0, 0.0
        else:
            sc = self._stage_cfg(stage)
            optics = stage == "stage1"
            groups = param_groups(self.hl.lens if optics else None, self.hl.doe if optics else None, self.net,
                                  lr_lens=sc.lr_lens, lr_doe=sc.lr_doe, lr_network=sc.lr_network)
            total, warm, minr = self.total_steps(stage), sc.warmup_steps, sc.min_lr_ratio
        opt = build_optimizer(groups)
        return opt, warmup_cosine_scheduler(opt, max(total, 1), min(warm, max(total - 1, 0)), minr)

    # ------------------------------------------------------------------ data
    def _batch(self, stage: str, step: int) -> torch.Tensor:
        sc = self._stage_cfg(stage)
        n = len(self.train_data)
        per_epoch = max(n // sc.batch_size, 1)
        epoch, b = divmod(step, per_epoch)
        epoch += 1000 if stage == "stage2" else 0  # other crops than stage 1's
        perm = torch.randperm(n, generator=_epoch_generator(self.cfg.seed, epoch), device="cpu")
        if hasattr(self.train_data, "set_epoch"):
            self.train_data.set_epoch(epoch)
        idx = [int(perm[(b * sc.batch_size + i) % n]) for i in range(sc.batch_size)]
        return torch.stack([self.train_data[i] for i in idx]).to(self.device, self.dtype)

    def _extent(self, size_px, centre_uv) -> tuple:
        """Normalised extent (u0, u1, v0, v1) of an h×w patch at the sensor pitch centred at ``centre_uv``."""
        h, w = size_px
        du, dv = w * self.pitch / (0.5 * self.sensor_size[0]), h * self.pitch / (0.5 * self.sensor_size[1])
        if du > 2 or dv > 2:
            raise ValueError(f"a {h}×{w} patch at {self.pitch * 1e3:g} µm pixels is larger than the "
                             f"{self.sensor_size[0]:g}×{self.sensor_size[1]:g} mm sensor")
        u = min(max(centre_uv[0], -1 + du / 2), 1 - du / 2)
        v = min(max(centre_uv[1], -1 + dv / 2), 1 - dv / 2)
        return (u - du / 2, u + du / 2, v - dv / 2, v + dv / 2)

    def _random_extent(self, size_px, pm=None) -> tuple:
        """A patch at a uniformly random place on the sensor (the run's generator). With the map ``pm`` whose
        PSFs are dark at some nodes (the DOE aperture or vignetting blocks all their light), the place is drawn
        again until its nearest node is lit (:meth:`_lit_uv`): a patch of a black image teaches the network to
        invent it."""
        uv = self._random_uv()
        if pm is not None:
            uv = self._lit_uv(uv, pm.positions, _lit_nodes(pm))
        return self._extent(size_px, uv)

    def _random_uv(self) -> tuple[float, float]:
        """A uniformly random place ``(u, v)`` on the sensor (normalised coordinates, the run's generator)."""
        uv = torch.rand(2, generator=self.gen, dtype=torch.float64, device="cpu") * 2 - 1
        return float(uv[0]), float(uv[1])

    def _lit_uv(self, uv, positions, lit) -> tuple[float, float]:
        """``uv`` if its nearest node of ``positions`` (N, M, 2) is lit (``lit`` (N, M) bool, or None: all are),
        else a new :meth:`_random_uv` until one is (at most :data:`_LIT_DRAWS` draws in all); warns once
        (:class:`DarkRegionWarning`) where some node is dark. A fully lit map draws nothing more."""
        if lit is None:
            return uv
        for _ in range(_LIT_DRAWS - 1):
            if bool(lit[_nearest_node(positions, torch.tensor(uv, dtype=torch.float64, device=positions.device))]):
                break
            uv = self._random_uv()
        n, k = int(lit.numel()), int((~lit).sum())
        self._warn_once(f"{k} of the {n} nodes of the {tuple(lit.shape)} PSF map receive no light (the DOE "
                        "aperture or vignetting blocks it): training patches are placed around the lit nodes "
                        "only; a DOE that covers every field's beam (lens.doe_size) avoids the dark regions",
                        DarkRegionWarning)
        return uv

    # ------------------------------------------------------------------ optics
    def step_nodes(self, generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """This step's PSF-map nodes: field angles ``(F, 2)`` (deg) and normalised sensor positions ``(N, M, 2)``.

        ``optics.field_jitter`` 0: the fixed cell centres. Otherwise the whole grid is shifted by one offset drawn
        from ``generator`` (default the run's), uniform in ±field_jitter/2 of a cell, and the field angles of
        the shifted nodes are found (chief-ray mapping at the first depth, as for the fixed grid); the
        DOE-field cache is emptied (the shifted nodes' fields are never asked for again)."""
        from raywave.imaging.psfmap import fields_at, normalised_grid

        jit = float(self.cfg.optics.field_jitter)
        if jit <= 0:
            return self.fields, self.positions
        n, m = self.grid
        r = torch.rand(2, generator=self.gen if generator is None else generator, dtype=torch.float64, device="cpu")
        pos = normalised_grid(self.grid, device="cpu") + (r - 0.5) * jit * torch.tensor([2.0 / m, 2.0 / n],
                                                                          dtype=torch.float64, device="cpu")
        half = torch.tensor([0.5 * self.sensor_size[0], 0.5 * self.sensor_size[1]], dtype=torch.float64, device="cpu")
        with torch.no_grad():
            fields = fields_at(self.hl, pos * half, depth=self.depths[0]).reshape(-1, 2)
        if self.cache is not None:
            self.cache.clear()
        return fields, pos.to(self.device)

    def _replay_chunk(self) -> int:
        """Field points per chunk of a step's map: ``optics.chunk``, or for ``auto`` :func:`auto_chunk` from the
        device's free memory and the DOE's simulation grid (3 wavelengths a source in stage 1)."""
        chunk = self.cfg.optics.chunk
        if chunk != "auto":
            return int(chunk)
        doe = getattr(self.hl, "doe", None)
        shape = doe.sim_shape(1) if hasattr(doe, "sim_shape") else (0, 0)
        return auto_chunk(self.fields.shape[0], 3, int(shape[0]) * int(shape[1]), self.device,
                          traced=self.cache is None)

    def optics_step(self, grid_fields=None, wavelengths=None) -> OpticsStep:
        """The step's PSF map as an :class:`OpticsStep`: chunks = (depth, :attr:`chunk` field points); outputs
        psf ``(D·F, 3, ks, ks)`` and centres ``(D·F, 3, 2)``; one wavelength per channel drawn from the run's
        generator. ``wavelengths`` ``(W,)`` µm: these instead (outputs ``(D·F, W, ...)``), no draw (the
        generator is not touched)."""
        from raywave.imaging.psfmap import psf_map_points

        fields = self.fields if grid_fields is None else grid_fields
        ranges = chunk_ranges(fields.shape[0], self.chunk)
        nf = len(ranges)
        oc = self.cfg.optics

        model, kw = self.recon_model, self._map_kwargs(self.recon_model)

        def compute(ctx):
            d, c = divmod(ctx.index, nf)
            with self.surface_warnings():  # sampling / vignetting warnings: once per run, not per step
                res = psf_map_points(model, fields[ranges[c].start:ranges[c].stop], ctx.draws, self.depths[d],
                                     oc.ks, **kw)
            self._count_psfs(res.psf.shape[0] * res.psf.shape[1])
            return res.psf, res.center

        if wavelengths is not None:
            draws = torch.as_tensor(wavelengths, dtype=torch.float64, device="cpu")
            return OpticsStep(compute, nf * len(self.depths), draws=draws)
        return OpticsStep.draw(compute, nf * len(self.depths), lambda g: self.color.sample(g), self.gen)

    def _as_map(self, psf, cen):
        """(D·F, 3, ks, ks), (D·F, 3, 2) → (D, 3, N, M, ks, ks), (D, 3, N, M, 2)."""
        D, (N, M), ks = len(self.depths), self.grid, psf.shape[-1]
        p = psf.reshape(D, N, M, 3, ks, ks).permute(0, 3, 1, 2, 4, 5)
        c = cen.reshape(D, N, M, 3, 2).permute(0, 3, 1, 2, 4)
        return p, c

    def simulate(self, img, psf_d, cen_d, extent, positions=None):
        """Render one object plane: ``img (B, 3, h, w)`` linear, PSFs ``(3, N, M, ks, ks)``, centres
        ``(3, N, M, 2)`` mm, the patch's normalised sensor ``extent``."""
        from raywave.imaging.render import render

        return render(img, psf_d, positions=self.positions if positions is None else positions, centers=cen_d,
                      sensor_size=self.sensor_size, pitch=self.pitch, extent=extent)

    def _sensor(self):
        from raywave.imaging.sensor import Sensor

        sc = self.cfg.stage2
        return Sensor.from_electrons(full_well=sc.full_well, read_noise=sc.read_noise)

    def evaluation_map(self, model=None):
        """The stage-2 / evaluation PSF map of ``model`` (default the reconstruction's, :attr:`recon_model`):
        ``optics.eval_grid``, all wavelengths averaged per channel."""
        oc = self.cfg.optics
        model = self.recon_model if model is None else model
        wls = self.color.all_wavelengths()
        # no DOE-field cache: each of the map's sources is built once, and the engine's own groups (hundreds of
        # sources a call) are ~10 % faster than the cache's calls of a few field points; a large map is resumable
        kw = {**self._map_kwargs(model), "cache": None}
        n_psfs = len(self.depths) * wls.numel() * int(oc.eval_grid[0]) * int(oc.eval_grid[1])
        folder = self.run_dir / f"eval_map_{type(model).__name__}" if n_psfs >= RESUMABLE_MAP_PSFS else None
        with self.surface_warnings():
            pm = _resumable_map(folder, model, grid=tuple(oc.eval_grid), depths=self.depths, wavelengths=wls,
                                ks=self.eval_ks, progress=self.progress, **kw)
        out = pm.channel_average(self.color).detach()
        if pm.energy_outside is not None:
            lost = float(pm.energy_outside.max())
            out.info["energy_outside_max"] = lost
            if lost > 0.01:
                self._warn_once(f"the evaluation PSF window (optics.eval_ks = {self.eval_ks}) misses up to "
                                f"{lost:.1%} of a PSF's energy: raise optics.eval_ks", CropWarning)
        return out

    def truth_map(self):
        """The evaluation map of the hybrid lens itself (ray-wave model), with which the evaluation simulates the
        sensor images: the stage-2 map when the reconstruction uses the lens's own PSFs, else computed once."""
        if self.recon_model is self.hl:
            if self.stage2_map is None:
                self.stage2_map = self.evaluation_map()
            return self.stage2_map
        if self._truth_map is None:
            self._truth_map = self.evaluation_map(self.hl)
        return self._truth_map

    # ------------------------------------------------------------------ warnings: surfaced once per run
    @contextlib.contextmanager
    def surface_warnings(self):
        """Record the warnings raised inside (sampling, vignetting, crop, ...) and re-issue each kind once per
        run (deduplicated by category and message with its numbers masked), also recording it in
        ``warnings.jsonl`` of the run folder."""
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            yield
        for w in caught:
            self._warn_once(str(w.message), w.category, _kind(w.message))

    def _warn_once(self, message: str, category=UserWarning, kind: str | None = None) -> None:
        """Issue ``message`` once per run: warnings of one ``kind`` (default: the message with its numbers masked)
        and category are shown (and logged to ``warnings.jsonl``) the first time only."""
        key = (getattr(category, "__name__", str(category)),
               kind if kind is not None else re.sub(r"[-+]?\d[\d.e+-]*", "#", message))
        if key in self._seen_warnings:
            return
        self._seen_warnings.add(key)
        path = self.run_dir / "warnings.jsonl"
        with open(path, "a") as fh:
            fh.write(json.dumps({"warning": key[0], "message": message}) + "\n")
        # attributed to the run's warnings.jsonl; line 0 because Python prints the source line of the location it
        # is given, which here would be the JSON record of the same warning (each warning showed twice)
        warnings.warn_explicit(message, category, str(path), 0)


    # ------------------------------------------------------------------ progress inside a step
    @contextlib.contextmanager
    def _step_progress(self, stage: str, step: int):
        """A second tqdm bar (PSFs computed in this step: the forward pass and its replay, each chunk's PSFs) shown
        while one optimizer step runs, when it takes longer than 2 s: a first step that fills the DOE-field cache
        computes the whole map and takes minutes (the step bar alone would sit at 0)."""
        from tqdm.auto import tqdm

        self._psf_bar = tqdm(total=None, unit="PSF", desc=f"  {stage} step {step + 1}: PSFs", leave=False,
                             position=1, delay=2.0, disable=not self.progress)
        try:
            yield
        finally:
            self._psf_bar.close()
            self._psf_bar = None

    def _count_psfs(self, n: int) -> None:
        """``n`` more PSFs computed in the current step (:meth:`_step_progress`)."""
        bar = getattr(self, "_psf_bar", None)
        if bar is not None:
            bar.update(int(n))

    # ------------------------------------------------------------------ the loop
    def _modules(self) -> dict:
        return {"hybrid": self.hl, "net": self.net}

    def _log(self, rec: dict) -> None:
        with open(self.log_path, "a") as fh:
            fh.write(json.dumps(rec) + "\n")

    def run(self, resume: bool = True, stop_after: int | None = None) -> dict:
        """Run (or resume) all stages; returns ``{"stage": ..., "step": ...}`` where it stopped.
        ``stop_after``: stop after this many optimizer steps in this call (tests)."""
        from tqdm.auto import tqdm

        stage, step = "pre", 0
        ck = latest_checkpoint(self.run_dir) if resume else None
        info = None
        if ck is not None:
            extra = torch.load(ck, map_location="cpu", weights_only=True)["extra"]
            stage, step = extra["stage"], int(extra["stage_step"])
            if stage == "done":  # a finished run: continue with its trained modules (nothing is left to train)
                load_checkpoint(ck, modules=self._modules(), generators={"train": self.gen})
        done_here = 0
        while stage != "done":
            total = self.total_steps(stage)
            if stage == "stage2" and total > 0 and self.stage2_map is None:
                self.hl.requires_grad_(False)
            opt, sched = self._optimizer(stage) if total > 0 else (None, None)
            if ck is not None and info is None:
                fresh = step == 0  # a stage-boundary checkpoint: the next stage starts with a new optimizer
                info = load_checkpoint(ck, modules=self._modules(), optimizer=None if fresh else opt,
                                       scheduler=None if fresh else sched, generators={"train": self.gen})
            else:
                info = info or {}
            bar = tqdm(total=total, initial=step, desc=f"{'baseline ' if self.baseline else ''}{stage}",
                       unit="step", disable=not self.progress)
            while step < total:
                if stop_after is not None and done_here >= stop_after:
                    bar.close()
                    return {"stage": stage, "step": step}
                t0 = time.perf_counter()
                self._fabrication(stage, step)
                with self._step_progress(stage, step):
                    if stage == "pre":
                        loss = self._pre_step(opt, sched)
                    elif stage == "stage1":
                        loss = self._stage1_step(step, opt, sched)
                    else:
                        loss = self._stage2_step(step, opt, sched)
                if not math.isfinite(loss):
                    raise FloatingPointError(f"{stage} step {step}: the loss is {loss} (check the learning rates)")
                step += 1
                done_here += 1
                self._log({"stage": stage, "step": step, "loss": loss, "time_s": time.perf_counter() - t0})
                bar.set_postfix(loss=f"{loss:.4g}")
                bar.update(1)
                if step % int(self.cfg.checkpoint_every) == 0 or step == total:
                    self._save(stage, step, opt, sched)
            bar.close()
            stage, step = STAGES[STAGES.index(stage) + 1], 0
            if stage != "done":
                info = {}
        self.hl.requires_grad_(False)
        self._fabrication("done", 0)
        return {"stage": "done", "step": 0}

    def _save(self, stage, step, opt, sched) -> None:
        keep = sorted((self.run_dir / "checkpoints").glob("step_*.pt"))[-1:]  # the previous one stays too
        for old in set((self.run_dir / "checkpoints").glob("step_*.pt")) - set(keep):
            old.unlink()
        end = step >= self.total_steps(stage)
        save_checkpoint(checkpoint_path(self.run_dir, self._global_step(stage, step)), modules=self._modules(),
                        optimizer=None if end else opt, scheduler=None if end else sched, step=step,
                        generators={"train": self.gen},
                        extra={"stage": stage, "stage_step": step} if step < self.total_steps(stage)
                        else {"stage": STAGES[STAGES.index(stage) + 1], "stage_step": 0})

    def _global_step(self, stage, step) -> int:
        off = 0
        for s in STAGES[:STAGES.index(stage)]:
            off += self.total_steps(s)
        return off + step

    def restore(self, path=None) -> dict:
        """Load the modules (lens, DOE, network) of ``path`` (default the run folder's latest checkpoint), for
        evaluation; optimizer and random states are not touched."""
        path = latest_checkpoint(self.run_dir) if path is None else Path(path)
        if path is None:
            raise FileNotFoundError(f"{self.run_dir}: no checkpoint")
        info = load_checkpoint(path, modules=self._modules(), restore_rng=False)
        extra = torch.load(path, map_location="cpu", weights_only=True).get("extra", {})
        self._fabrication(extra.get("stage", "done"), int(extra.get("stage_step", 0)))
        return info

    # ------------------------------------------------------------------ evaluation and export (training/evaluation.py)
    def eval_images_tensor(self) -> torch.Tensor:
        """Held-out images ``(B, 3, S, S)`` (:func:`raywave.training.evaluation.eval_images`)."""
        from raywave.training.evaluation import eval_images

        return eval_images(self)

    def evaluate(self, noise: bool = True) -> dict:
        """PSNR/SSIM of the held-out images per depth and field zone for every reconstruction
        (:func:`raywave.training.evaluation.evaluate`, which lists the keys)."""
        from raywave.training.evaluation import evaluate

        return evaluate(self, noise)

    # ------------------------------------------------------------------ ablation: a plain network, same optics
    def train_plain_network(self, progress: bool | None = None) -> "Trainer":
        """Train a plain network (``network.deconv: none``, stage 2's settings and steps, the same seed) on this
        run's final optics, in ``run_dir/plain_network`` (resumable); it becomes :attr:`plain_net`, evaluated
        as ``psnr_network_only``. Returns its Trainer."""
        cfg = copy.deepcopy(self.cfg)
        cfg.network.deconv, cfg.network.ablation = "none", False
        cfg.pre_stage.steps, cfg.stage1.max_steps = 0, 0
        self.hl.requires_grad_(False)
        plain = Trainer(cfg, self.run_dir / "plain_network", hybrid=self.hl, baseline=False, field_cache=self.cache,
                        progress=self.progress if progress is None else progress, train_data=self.train_data,
                        eval_images=self.eval_images)
        plain.stage2_map = self.stage2_map if self.stage2_map is not None else self.evaluation_map()
        self.stage2_map = plain.stage2_map
        plain.run()
        self.plain_net = plain.net
        return plain

    def export(self, folder=None) -> Path:
        """Write the element that was evaluated into ``run_dir/final`` (or ``folder``):
        :func:`raywave.training.evaluation.export` lists the files."""
        from raywave.training.evaluation import export

        return export(self, folder)
