"""Baselines of a training run (``TrainConfig.baseline``): the DOE the designed system is compared with.

* ``"blank"``: a zero-phase DOE (the lens alone), frozen; the same network training.
* ``"paraxial"``: the DOE **designed with the paraxial wave model** (:class:`~raywave.models.ParaxialModel`: an
  ideal thin lens of the lens's paraxial focal length + the DOE + angular-spectrum propagation, blind to the
  refractive lens's aberrations) and then **evaluated with the ray-wave model**: the paper's EDoF baseline
  (supplement section 2.6), i.e. what a conventional paraxial "deep optics" design delivers on the real lens.

The paraxial design minimises the pre-stage's PSF objective (:mod:`raywave.training.losses`): the mean RMS
radius (measured about ``pre_stage.about``) of the PSFs of the stage-1 field grid at every depth plus
``pre_stage.similarity_weight`` × the mean L1 distance between the PSFs of different depths, with Adam
(``pre_stage.lr_doe``) for ``baseline_steps`` steps, one wavelength per colour channel drawn per step from a
generator seeded with ``seed`` (as the pre-stage), and with ``optics.field_jitter`` the grid's nodes shifted at
random each step (as in the pre-stage). The paraxial model acts on the same :class:`~raywave.doe.PixelDOE`
module as the hybrid lens, so the designed phase is the ray-wave lens's DOE as it stands. The DOE is then frozen
and the baseline's network is trained exactly like the blank baseline's.

:func:`prepare_baseline` (called by the :class:`~raywave.training.trainer.Trainer` of a baseline run) writes
``baseline_design.json`` into the run folder: the objective before (blank DOE) and after the design, under the
paraxial model (what was optimised) and under the ray-wave model (what the real lens does with it).
"""

from __future__ import annotations

import json
import time

import torch

from raywave.training.losses import psf_restorability_loss, psf_similarity_loss, psf_size_loss

__all__ = ["BASELINES", "psf_objective", "objective_settings", "model_objective", "design_paraxial_doe",
           "prepare_baseline"]

BASELINES = ("blank", "paraxial")


def psf_objective(psf: torch.Tensor, similarity_weight: float = 0.0, about: str = "centroid",
                  restore_weight: float = 0.0, restore_noise: float = 1e-3,
                  restore_filter: str = "shared") -> torch.Tensor:
    """The pre-stage objective of PSFs ``(D, ..., ks, ks)`` (D depths first): mean RMS radius (pixels, about
    each PSF's ``about``: ``"centroid"`` or ``"center"``) plus ``similarity_weight`` × mean L1 distance across
    depths (when D > 1) plus ``restore_weight`` × the restorability term (dB, the soft worst depth's expected
    error of one Wiener filter for all depths, or with ``restore_filter="own"`` of each depth's own filter, at
    noise ``restore_noise``, :func:`~raywave.training.losses.psf_restorability_loss`). Scalar."""
    loss = psf_size_loss(psf, about=about)
    if similarity_weight and psf.shape[0] > 1:
        loss = loss + similarity_weight * psf_similarity_loss(psf)
    if restore_weight:
        loss = loss + restore_weight * psf_restorability_loss(psf, noise=restore_noise, filter=restore_filter)
    return loss


def objective_settings(pre_stage) -> dict:
    """The keyword arguments of :func:`psf_objective` that a :class:`~raywave.training.config.PreStageConfig`
    sets (the designed run's pre-stage and the paraxial baseline share them)."""
    kw = {"similarity_weight": float(pre_stage.similarity_weight), "about": pre_stage.about}
    if pre_stage.restore_weight:  # only when used: older stored baseline designs stay reusable
        kw.update(restore_weight=float(pre_stage.restore_weight), restore_noise=float(pre_stage.restore_noise))
        if pre_stage.restore_filter != "shared":
            kw["restore_filter"] = pre_stage.restore_filter
    return kw


def model_objective(model, fields, depths, wavelengths, ks: int, similarity_weight: float = 0.0,
                    about: str = "centroid", objective: dict | None = None, **psf_kw) -> torch.Tensor:
    """:func:`psf_objective` of ``model``'s PSFs (``psf_result``) at ``fields`` ``(F, 2)`` (deg), each of
    ``depths`` (mm) and ``wavelengths`` (µm); differentiable w.r.t. the model's DOE. ``objective``: further
    keyword arguments of :func:`psf_objective` (the restorability term). Scalar."""
    wls = [float(w) for w in wavelengths]
    # sampling / crop warnings propagate: the Trainer surfaces them once per run (Trainer.surface_warnings)
    psf = torch.stack([model.psf_result(fields, wls, ks=ks, depth=d, **psf_kw).psf for d in depths])
    return psf_objective(psf, similarity_weight, about=about, **(objective or {}))


def design_paraxial_doe(hybrid, fields, depths, sample_wavelengths, ks: int, steps: int, lr: float,
                        similarity_weight: float = 0.0, generator: torch.Generator | None = None,
                        about: str = "centroid", objective: dict | None = None) -> list[float]:
    """Optimise ``hybrid``'s DOE **in place** with the paraxial wave model.

    Args:
        hybrid: the :class:`~raywave.hybrid.HybridLens`; only its DOE's parameters change (the refractive
            lens gives the paraxial model its EFL, pupil and field points).
        fields: ``(F, 2)`` field angles (deg), or ``f(generator) -> (F, 2)``: each step's (e.g. the jittered
            nodes of :meth:`~raywave.training.trainer.Trainer.step_nodes`), drawn after the wavelengths.
        depths: object distances (mm; ``inf`` distant).
        sample_wavelengths: ``f(generator) -> (C,)`` wavelengths (µm) of one step (e.g. ``ColorSpec.sample``).
        ks: PSF size (sensor pixels).
        steps, lr: Adam steps and learning rate (rad per step, roughly).
        similarity_weight: weight of the cross-depth similarity term.
        generator: the wavelength draws' generator.
        about: where the PSF size is measured from (:func:`psf_objective`; the pre-stage's ``about``).
        objective: further keyword arguments of :func:`psf_objective` (``restore_weight``, ``restore_noise``).

    Returns:
        the objective (paraxial model) at each step, before that step's update.
    """
    from raywave.models import make_model

    if int(steps) < 0:
        raise ValueError(f"baseline_steps must be >= 0, got {steps}")
    model = make_model("paraxial", hybrid)
    doe = hybrid.doe
    params = list(doe.parameters())
    was = [p.requires_grad for p in params]
    for p in params:
        p.requires_grad_(True)
    opt = torch.optim.Adam(params, lr=float(lr))
    history = []
    try:
        for _ in range(int(steps)):
            wls = sample_wavelengths(generator)
            step_fields = fields(generator) if callable(fields) else fields
            loss = model_objective(model, step_fields, depths, wls, ks, similarity_weight, about, objective)
            if not torch.isfinite(loss):
                raise FloatingPointError(f"paraxial baseline design: the objective is {float(loss)} "
                                         "(check pre_stage.lr_doe)")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            history.append(float(loss.detach()))
    finally:
        for p, w in zip(params, was):
            p.requires_grad_(w)
            p.grad = None
    return history


def _objectives(trainer, models: dict, wls) -> dict:
    """The objective of each model at all the run's wavelengths (no autograd)."""
    cfg = trainer.cfg
    kw_obj = objective_settings(cfg.pre_stage)
    w, about = kw_obj.pop("similarity_weight"), kw_obj.pop("about")
    out = {}
    with torch.no_grad():
        for name, (model, kw) in models.items():
            out[name] = float(model_objective(model, trainer.fields, trainer.depths, wls, cfg.optics.ks, w, about,
                                              kw_obj, **kw))
    return out


def _settings(cfg) -> dict:
    """Everything the paraxial design depends on (a stored design with other settings is not reused)."""
    from raywave.training.config import to_dict

    d = {"seed": cfg.seed, "steps": cfg.baseline_steps, "lr_doe": cfg.pre_stage.lr_doe,
         **objective_settings(cfg.pre_stage),
         "lens": to_dict(cfg.lens), "grid": cfg.optics.grid, "field_jitter": cfg.optics.field_jitter,
         "depths": cfg.optics.depths, "ks": cfg.optics.ks, "wavelengths": cfg.optics.wavelengths}
    for key in ("doe_wavelength", "doe_material", "doe_levels"):  # the continuous design's dispersion (only when
        if getattr(cfg.optics, key) is not None:                  # set: older stored designs stay reusable)
            d[key] = getattr(cfg.optics, key)
    return json.loads(json.dumps(d))


def _write_atomic(path, write) -> None:
    import os

    tmp = path.with_name(path.name + ".tmp")
    write(tmp)
    os.replace(tmp, path)


_OLD_DEFAULTS = {"about": "centroid", "field_jitter": 0.0}


def _stored_design(trainer, settings: dict) -> dict | None:
    """The run folder's ``baseline_design.json`` record with its DOE loaded into the trainer's hybrid lens, when
    it was made with ``settings``; else None."""
    folder = trainer.run_dir
    try:
        rec = json.loads((folder / "baseline_design.json").read_text())
        # records written before these settings existed were designed with their present defaults
        if {**_OLD_DEFAULTS, **rec.get("settings", {})} != settings:
            return None
        state = torch.load(folder / "baseline_doe.pt", map_location="cpu", weights_only=True)
        trainer.hl.doe.load_state_dict(state)
    except (OSError, ValueError, KeyError, RuntimeError):
        return None
    return rec


def prepare_baseline(trainer) -> dict | None:
    """Set up the DOE of a baseline :class:`~raywave.training.trainer.Trainer` (``trainer.baseline`` true)
    according to ``trainer.cfg.baseline`` (the DOE arrives zeroed and frozen): ``"blank"`` keeps it (returns
    None); ``"paraxial"`` designs it (:func:`design_paraxial_doe`) and stores the design in the run folder
    (``baseline_doe.pt``, ``baseline_design.json``: the objectives before/after and the settings), or loads the
    stored design when its settings are this config's (resume, ``--restart``, ``raywave eval``). Returns the
    record."""
    import torch.distributed as dist

    from raywave.models import make_model

    cfg = trainer.cfg
    kind = cfg.baseline
    if kind not in BASELINES:
        raise ValueError(f"baseline must be one of {', '.join(BASELINES)}, got {kind!r}")
    if kind == "blank":
        return None
    settings = _settings(cfg)
    rec = _stored_design(trainer, settings)
    if rec is not None:
        return rec
    hl = trainer.hl
    models = {"paraxial": (make_model("paraxial", hl), {}),
              "ray_wave": (make_model("raywave", hl, rays=cfg.optics.rays), {})}
    wls = trainer.color.all_wavelengths().tolist()
    with trainer.surface_warnings():
        before = _objectives(trainer, models, wls)
        gen = torch.Generator().manual_seed(int(cfg.seed) * 31 + 7)
        t0 = time.perf_counter()
        kw_obj = objective_settings(cfg.pre_stage)
        w, about = kw_obj.pop("similarity_weight"), kw_obj.pop("about")
        history = design_paraxial_doe(hl, lambda g: trainer.step_nodes(g)[0], trainer.depths, trainer.color.sample,
                                      cfg.optics.ks, cfg.baseline_steps, cfg.pre_stage.lr_doe, w, gen,
                                      about=about, objective=kw_obj)
        seconds = time.perf_counter() - t0
        after = _objectives(trainer, models, wls)
    rec = {"baseline": kind, "design_seconds": seconds, "objective_blank": before, "objective_designed": after,
           "history_paraxial": history, "settings": settings,
           "note": "objective = mean RMS PSF radius (pixels) + similarity_weight × mean L1 PSF distance across "
                   "depths (+ restore_weight × the worst depth's expected Wiener error in dB when set), at all the "
                   "run's wavelengths on the stage-1 field grid"}
    if not (dist.is_available() and dist.is_initialized() and dist.get_rank() != 0):  # one writer per run
        state = {k: v.detach().cpu() for k, v in hl.doe.state_dict().items()}
        _write_atomic(trainer.run_dir / "baseline_doe.pt", lambda p: torch.save(state, p))
        _write_atomic(trainer.run_dir / "baseline_design.json",
                      lambda p: p.write_text(json.dumps(rec, indent=2) + "\n"))
    return rec
