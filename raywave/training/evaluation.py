"""Evaluation and export of a :class:`~raywave.training.trainer.Trainer`'s design: the held-out images, PSNR/SSIM
per depth and field zone for every reconstruction of the ablation, and the export of exactly the element that was
evaluated (through the one fabrication path, :mod:`raywave.doe.export`). The Trainer's ``evaluate``,
``eval_images_tensor`` and ``export`` methods are these functions."""

from __future__ import annotations

from pathlib import Path

import torch

from raywave.training.losses import psf_size
from raywave.training.networks import PSFAwareNet

__all__ = ["eval_images", "evaluate", "export", "nearest_psf_size"]


def eval_images(trainer) -> torch.Tensor:
    """Held-out images ``(B, 3, S, S)``: centre crops (``data.eval_size``) of the evaluation photos (the
    sample pool's eval split, or the folder's ``valid`` split), linear if ``data.linear``; smaller photos
    are skipped."""
    from raywave.imaging.data import SamplePhotoDataset, srgb_to_linear

    if trainer.eval_images is not None:
        return trainer.eval_images.to(trainer.device, trainer.dtype)
    if trainer.cfg.data.source == "folder":
        ds = trainer._dataset("eval")
    else:
        ds = SamplePhotoDataset("eval", patch_size=None, linear=False)
    s = int(trainer.cfg.data.eval_size)
    out = []
    for i in range(ds.n_images):
        im = ds._image(i)  # sRGB-encoded, whole photo
        H, W = im.shape[-2:]
        if H < s or W < s:
            continue
        r, c = (H - s) // 2, (W - s) // 2
        im = im[:, r:r + s, c:c + s]
        out.append(srgb_to_linear(im) if trainer.cfg.data.linear else im)
    if not out:
        raise ValueError(f"no evaluation image is at least {s}×{s} pixels (data.eval_size)")
    return torch.stack(out).to(trainer.device, trainer.dtype)


@torch.no_grad()
def evaluate(trainer, noise: bool = True) -> dict:
    """PSNR/SSIM of the held-out images per depth and field zone (the image placed at the sensor centre and
    at a corner), with the evaluation map and (``noise``) a fixed-seed noise draw, for each reconstruction:

    * ``psnr`` / ``ssim``: the trained reconstruction (``network.deconv``: deconvolution + network, or the
      network alone);
    * ``psnr_input`` / ``ssim_input``: the simulated sensor image itself (the optics' share);
    * ``psnr_deconv`` / ``ssim_deconv``: the multi-Wiener deconvolution alone (``deconv: wiener``);
    * ``psnr_network_only`` / ``ssim_network_only``: a plain network trained on the same optics
      (``network.ablation``, :meth:`Trainer.train_plain_network`);
    * ``psnr_deconv_true`` / ``ssim_deconv_true``: for a baseline whose reconstruction uses the paraxial model's
      PSFs (``baseline_reconstruction: paraxial``), the same deconvolution given the lens's true PSFs (the
      baseline DOE compared alone);

    and ``psf_rms_px``: the RMS radius (sensor pixels, about the centroid, mean of the three channels) of the
    lens's evaluation-map PSF nearest the zone's centre; ``mean`` also has ``psf_rms_px_map`` (the whole map's
    mean) and ``energy_outside_max`` (the largest fraction of a PSF's energy outside the evaluation crop).

    The sensor images are always simulated with the lens's own (ray-wave) evaluation map
    (:meth:`Trainer.truth_map`); the reconstructions use the run's reconstruction map (``trainer.stage2_map``)."""
    from raywave.imaging.render import render
    from raywave.training.metrics import psnr, ssim

    pm = trainer.stage2_map if trainer.stage2_map is not None else trainer.evaluation_map()
    trainer.stage2_map = pm  # the reconstruction's map
    truth = trainer.truth_map()  # the lens's own (ray-wave) map: the sensor images; pm itself unless a baseline
    other = truth is not pm       # reconstructs with the paraxial model's PSFs (baseline_reconstruction)
    img = trainer.eval_images_tensor()
    sensor = trainer._sensor() if noise else None
    g = torch.Generator().manual_seed(12345)
    zones = {"centre": (0.0, 0.0), "edge": (0.8, 0.8)}
    out = {}

    def scores(x, name):
        x = x.clamp(0, 1).double()
        return {f"psnr{name}": float(psnr(x, img.double()).mean()), f"ssim{name}": float(ssim(x, img.double()).mean())}

    for d, depth in enumerate(trainer.depths):
        for zone, uv in zones.items():
            ext = trainer._extent(img.shape[-2:], uv)
            sim = render(img, truth.psf[d], positions=truth.positions, centers=truth.centers[d],
                         sensor_size=truth.sensor_size, pitch=truth.pitch, extent=ext)
            if sensor is not None:
                sim = sensor(sim, generator=g)
            exts = [ext] * img.shape[0]
            rec = trainer.reconstruct(sim, pm.psf, pm.centers, exts, pm.positions)
            row = {**scores(rec, ""), **scores(sim, "_input")}
            if isinstance(trainer.net, PSFAwareNet):
                row.update(scores(trainer.deconvolve(sim, pm.psf, pm.centers, exts, pm.positions), "_deconv"))
                if other:  # the same deconvolution given the lens's true PSFs: the DOE alone, compared
                    row.update(scores(trainer.deconvolve(sim, truth.psf, truth.centers, exts, truth.positions),
                                      "_deconv_true"))
            if trainer.plain_net is not None:
                row.update(scores(trainer.plain_net(sim), "_network_only"))
            row["psf_rms_px"] = nearest_psf_size(truth.psf[d], truth.positions, uv)
            out[f"depth={depth:g}/{zone}"] = row
    keys = list(next(iter(out.values())))
    out["mean"] = {k: sum(v[k] for v in out.values()) / len(out) for k in keys}
    out["mean"]["psf_rms_px_map"] = float(psf_size(truth.psf.double()).mean())
    if "energy_outside_max" in truth.info:
        out["mean"]["energy_outside_max"] = truth.info["energy_outside_max"]
    return out


def export(trainer, folder=None) -> Path:
    """Write the element that was evaluated into ``run_dir/final`` (one fabrication code path,
    :mod:`raywave.doe.export`):

    * ``lens.json`` + ``doe_phase.npy``: the lens with its DOE: the phase at the design wavelength (the
      fabricated profile: wrapped and quantised when ``optics.doe_levels`` is set) with its ``levels``,
      ``material`` and ``design_wavelength``, so that loading the file gives the evaluated DOE;
    * ``doe.pt``: the DOE module's state;
    * ``masks/masks.gds`` + ``masks/report.json``: the L-level map (L = ``optics.doe_levels``, default 16
      for a continuous design, which is then quantised for the masks only; the report says which) split
      into log2(L) binary masks.
    """
    import numpy as np

    from raywave.doe import save_doe
    from raywave.doe.export import export_design
    from raywave.io import write_lens_spec
    from raywave.lens.build import lens_to_spec

    folder = Path(folder) if folder is not None else trainer.run_dir / "final"
    folder.mkdir(parents=True, exist_ok=True)
    doe = trainer.hl.doe
    if getattr(doe, "phase_map", None) is None:
        raise ValueError(f"export: {type(doe).__name__} has no pixel phase map")
    with torch.no_grad():
        phase = doe.profile_pixels().detach().cpu().double().numpy()  # at λ0, as simulated
    np.save(folder / "doe_phase.npy", phase)
    save_doe(doe, folder / "doe.pt")
    spec = lens_to_spec(trainer.hl.lens)
    inside = getattr(trainer.hl, "after", None)  # a MidSystemLens: the DOE sits at a surface (issue 46)
    section = {"distance": trainer.hl.distance if inside is not None else trainer.hl.doe_distance,
               "pitch": doe.pitch, "shape": list(doe.shape),
               "aperture": doe.aperture, "phase": "doe_phase.npy", "design_wavelength": doe.design_wavelength}
    if getattr(trainer.hl, "oversample", 1) != 1:
        section["oversample"] = int(trainer.hl.oversample)
    if doe.material_name is not None:
        section["material"] = doe.material_name
    if doe.quant_levels is not None:
        section["levels"] = int(doe.quant_levels)
    elif doe.wrap:
        section["wrap"] = True
    if inside is not None:
        spec["surfaces"][inside]["doe"] = section
    else:
        spec["doe"] = section
    write_lens_spec(spec, folder / "lens.json")
    levels = doe.quant_levels if doe.quant_levels is not None else 16
    export_design(doe, levels, doe.material_name or _default_material(), doe.design_wavelength,
                  folder / "masks", name=trainer.cfg.name,
                  info={"evaluated_as_fabricated": doe.quant_levels is not None,
                        "note": "the masks are the DOE that was evaluated" if doe.quant_levels is not None
                        else "the design was trained and evaluated as a continuous phase (optics.doe_levels "
                             "unset); these masks quantise it for fabrication only"})
    return folder


def _default_material() -> str:
    from raywave.doe import DEFAULT_MATERIAL

    return DEFAULT_MATERIAL


def nearest_psf_size(psf_d, positions, uv) -> float:
    """RMS radius (pixels; :func:`~raywave.training.losses.psf_size`, mean over the channels) of the PSF of
    ``psf_d (C, N, M, ks, ks)`` whose node in ``positions (N, M, 2)`` is nearest the normalised point ``uv``."""
    d2 = (positions - torch.tensor(uv, dtype=positions.dtype, device=positions.device)).square().sum(-1)
    i, j = divmod(int(torch.argmin(d2)), d2.shape[1])
    return float(psf_size(psf_d[:, i, j].double()).mean())
