"""Training configuration: nested dataclasses ↔ YAML.

A run is described by one :class:`TrainConfig`; :func:`load_config` reads it from YAML, where any key left out
keeps its default and any **unknown key is an error naming the key (with its dotted path) and the file** (a
typo must never be silently ignored). :func:`dump_config` writes the fully resolved config (every field), which
is what a run folder stores. Distances in mm (``inf`` = distant object: YAML ``.inf`` or the string ``inf``),
wavelengths in µm, DOE pitch in mm, learning rates per parameter group.

Two sizes per application: the shipped ``configs/*.yaml`` are small CPU demos; the paper's sizes are given in
the comments of each file (and the field docstrings here).
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Union

__all__ = ["ConfigError", "RULES", "Rule", "LensConfig", "OpticsConfig", "DataConfig", "NetworkConfig", "PreStageConfig",
           "StageConfig", "TrainConfig", "from_dict", "to_dict", "load_config", "dump_config", "apply_overrides"]


class ConfigError(ValueError):
    """A config file is invalid: the message names the file and the key."""


@dataclass
class LensConfig:
    """The hybrid lens.

    Attributes:
        file: bundled lens name (``raywave lens list``) or path of a lens JSON/.zmx (with or without a DOE).
        doe: DOE parametrisation to learn: ``"pixel"`` (a free phase map), ``"zernike"`` (``doe_terms`` Noll
            Zernike coefficients over the DOE's inscribed disk: a smooth phase, what a DOE inside the lens needs:
            its phase is carried by rays, so pixel-scale noise is not modelled as diffraction), or ``"file"`` (the
            lens file's DOE).
        doe_terms: Zernike terms (Noll j = 1 .. doe_terms) of ``doe: zernike``.
        doe_pitch: DOE pixel pitch (mm); None: the file's or the default of :func:`raywave.hybrid.load_hybrid`.
        doe_size: DOE side (mm); None: as the file / sized to the beam.
        doe_distance: mm after the last vertex (with ``doe_after``: after that surface's vertex); None: the file's.
        doe_after: a DOE inside the lens (issue 46): the learned DOE sits ``doe_distance`` mm (default 0) after the
            vertex of surface ``doe_after``, inside the gap to the next surface, and the hybrid is a
            :class:`~raywave.hybrid.midsystem.MidSystemLens` (its PSFs trace every DOE-plane field again: no
            DOE-field cache). None: the DOE before the sensor, or a lens file's own DOE at a surface.
        train_lens: learn the refractive surfaces too (lr ``lr_lens``); False freezes the lens and caches the
            DOE-plane fields (the paper's aberration-correction set-up).
        focus_depth: refocus the sensor for an object at this distance (mm) before training (EDoF: 300 mm);
            None keeps the file's sensor position.
        sensor_pitch: PSF / image pixel pitch (mm); None: the lens's sensor pixel.
        sensor_size: sensor (w, h) mm, replacing the lens file's; None: the file's, or for a file without a sensor
            the square inscribed in the lens's image circle (:func:`raywave.lens.analysis.default_sensor_size`).
        stop_edge: where the ray-wave engine forms the stop's sharp edge: None (default) / "exit_pupil" (the
            stop's image, where it is physically sharp) or "doe" (the paper's model); see
            :class:`raywave.hybrid.HybridLens`. A DOE inside the lens (:class:`~raywave.hybrid.midsystem.
            MidSystemLens`): None is its default "auto" (per source the cut on its engine plane where that holds,
            else the exit-pupil edge), "doe" the cut for every source, "exit_pupil" the exit-pupil edge.
        edge_step: with the exit-pupil edge, how it reaches the DOE plane: None (the engine's default,
            "adaptive": per source the Fresnel step, or the DOE-plane cut where that is exact), "fresnel", "asm"
            or "auto"; see :data:`raywave.hybrid.hybrid_lens.EDGE_STEPS`.
    """

    file: str = "hybrid_asphere"
    doe: str = "pixel"
    doe_terms: int = 15
    doe_pitch: Optional[float] = None
    doe_size: Optional[float] = None
    doe_distance: Optional[float] = None
    doe_after: Optional[int] = None
    train_lens: bool = False
    focus_depth: Optional[float] = None
    sensor_pitch: Optional[float] = None
    sensor_size: Optional[list[float]] = None
    stop_edge: Optional[str] = None
    edge_step: Optional[str] = None


@dataclass
class OpticsConfig:
    """PSF maps used in training.

    Attributes:
        grid: PSF-map grid (rows, columns) in stage 1 (paper: 10×10; 5×5 for EDoF).
        eval_grid: grid for stage 2 and evaluation (paper: 40×40).
        depths: object distances (mm; ``inf`` distant). EDoF: [200, 300, 10000].
        ks: PSF size (sensor pixels).
        rays: traced nodes per PSF (None: the engine default).
        wavelengths: per colour channel R, G, B the candidate wavelengths (µm), one drawn per channel and
            iteration in stage 1, all averaged in stage 2 / evaluation.
        chunk: field points computed together in the map's forward pass and recomputed together in the replay
            (memory ∝ chunk), or ``auto`` (:func:`raywave.training.replay.auto_chunk`): on a GPU as many as a
            quarter of its free memory holds (fewer chunks: less host time a step), on a CPU 4.
        replay: use the memory-saving replay (False: one full autograd graph; small maps only).
        field_jitter: shift the whole ``grid`` of nodes by a random offset each pre-stage / stage-1 step,
            uniform in ±``field_jitter``/2 of a grid cell along x and y (drawn from the run's generator, so a
            resumed run replays it). 0: the fixed cell centres. 1: over the steps the nodes visit the whole
            sensor, so a pixel DOE cannot fit the PSFs at a few field points at the expense of the points
            between them (a coarse grid such as 3×3 otherwise invites that). The DOE-field cache then holds one
            step's fields only (the frozen lens is traced again each step: slower steps).
        eval_ks: PSF size (sensor pixels) of the stage-2 / evaluation map (None: ``ks``); large enough for the
            widest PSF of the map: the evaluation reports the energy outside the crop and warns above 1 %.
        doe_levels: train the DOE as the fabricated element (the path of ``raywave psf --doe-levels``): its
            phase wrapped at ``doe_wavelength`` and quantised to ``doe_levels`` levels (straight-through
            gradient), a dispersive height map in ``doe_material``; from stage-1 step ``fabricate_from`` on
            (before it, and in the pre-stage, the continuous height map). Stage 2, the evaluation and the
            export use the quantised element. None: a continuous phase throughout.
        doe_wavelength: design wavelength λ0 (µm) of the fabricated DOE (None: 0.55 µm).
        doe_material: the DOE's material (a glass name; None: FUSED_SILICA when the DOE is fabricated). Setting
            it (or ``doe_wavelength``) without ``doe_levels`` makes the continuous DOE dispersive.
        fabricate_from: stage-1 step from which the DOE is quantised (0: all of stage 1).
    """

    grid: list = field(default_factory=lambda: [10, 10])
    eval_grid: list = field(default_factory=lambda: [40, 40])
    depths: list = field(default_factory=lambda: [math.inf])
    ks: int = 32
    rays: Optional[int] = None
    wavelengths: dict = field(default_factory=lambda: {"R": [0.62, 0.66, 0.70], "G": [0.50, 0.53, 0.56],
                                                       "B": [0.45, 0.47, 0.49]})
    chunk: Union[int, str] = 1
    replay: bool = True
    field_jitter: float = 0.0
    eval_ks: Optional[int] = None
    doe_levels: Optional[int] = None
    doe_wavelength: Optional[float] = None
    doe_material: Optional[str] = None
    fabricate_from: int = 0


@dataclass
class DataConfig:
    """Training / evaluation images.

    Attributes:
        source: ``"samples"`` (the offline photo pool, fixed split), ``"folder"`` (``root``, DIV2K-style
            ``train``/``valid`` sub-folders) or ``"dead_leaves"`` (procedural, evaluation on the photo pool).
        root: image folder for ``source: folder``.
        patch_size: training crop (pixels).
        patches_per_image: crops per photo and epoch.
        eval_size: evaluation crop (centre crop, pixels).
        linear: train on linear intensities (sRGB-decoded); see :mod:`raywave.imaging.data`.
        dead_leaves_count: patches per epoch for ``source: dead_leaves``.
    """

    source: str = "samples"
    root: Optional[str] = None
    patch_size: int = 128
    patches_per_image: int = 8
    eval_size: int = 256
    linear: bool = True
    dead_leaves_count: int = 256


@dataclass
class NetworkConfig:
    """Reconstruction network: ``kind`` ``"unet"`` or ``"nafnet"``; ``width``; ``depth`` (UNet levels) or
    ``enc_blocks``/``middle_blocks`` (NAFNet).

    ``deconv``: ``"wiener"``: the PSF-aware reconstruction: a multi-Wiener deconvolution with the current PSF
    map (:mod:`raywave.imaging.deconv`; learned regularisation per channel, initial ``wiener_lambda`` and
    ``wiener_mu``; ``wiener_chroma``: ρ of the colour prior, the chroma's prior power relative to the
    luminance's, learned from this start; None: the per-channel filter), refined by the network, differentiable
    w.r.t. the PSFs (so the optics learn to be restorable); ``"wiener_select"``: the same, but with several
    ``optics.depths`` the image is deconvolved with each depth's map and the results are blended per region by
    the depth the image's own evidence favours (:mod:`raywave.imaging.depth`; ``select_temperature`` 1 is the
    Gaussian model's posterior) instead of one expected-error filter for all depths; ``"none"``: the paper's
    plain network on the sensor image.
    ``ablation``: after training, also train a plain network (``deconv: none``, stage 2's settings) on the final
    optics, for the ablation table of the evaluation (sensor image / network only / deconvolution + network).
    """

    kind: str = "nafnet"
    width: int = 16
    depth: int = 3
    enc_blocks: list = field(default_factory=lambda: [1, 1, 1])
    middle_blocks: int = 1
    deconv: str = "none"
    wiener_lambda: float = 1e-3
    wiener_mu: float = 1e-2
    wiener_chroma: Optional[float] = None
    select_temperature: float = 1.0
    ablation: bool = False


@dataclass
class PreStageConfig:
    """PSF-only optimisation before end-to-end training: minimise the PSF size (second moment), plus the
    dissimilarity across depths (EDoF) with weight ``similarity_weight``. ``steps: 0`` skips it. ``about``: the
    PSF size is the RMS radius about the PSF's ``"centroid"`` (sharpness only) or about the chief-ray pixel
    (``"center"``: also penalises a DOE that displaces the image point, i.e. adds distortion, which the
    evaluation against the undistorted scene counts as error). ``restore_weight`` (pixels per dB) adds the
    restorability term: the soft worst depth's expected error (dB) of one Wiener filter for all depths, with a
    natural-image spectrum and white noise of variance ``restore_noise`` relative to the image's
    (:func:`raywave.training.losses.psf_restorability_loss`); ``restore_filter: own`` gives each depth its own
    filter instead (the reconstruction of ``network.deconv: wiener_select``, which finds the depth from the image).
    The paraxial baseline minimises the same objective."""

    steps: int = 0
    lr_doe: float = 1e-1
    lr_lens: float = 1e-4
    similarity_weight: float = 0.0
    about: str = "centroid"
    restore_weight: float = 0.0
    restore_noise: float = 1e-3
    restore_filter: str = "shared"


@dataclass
class StageConfig:
    """One training stage (1: end-to-end without noise; 2: optics frozen, network fine-tuned with noise).

    Attributes:
        epochs, batch_size: as usual; ``micro_batches`` splits a batch for gradient accumulation.
        max_steps: stop after this many optimizer steps (None: epochs decide).
        lr_lens, lr_doe, lr_network: Adam learning rates per parameter group (paper: 1e-4, 1e-1, 1e-4).
        warmup_steps: linear warm-up, then cosine annealing to ``min_lr_ratio`` × lr at the last step.
        noise: add sensor noise (stage 2).
        read_noise, full_well: Poisson–Gaussian sensor noise: read noise (electrons) and full-well capacity.
        loss: ``"l1"``, ``"mse"`` or ``"edof"`` (issue 7's cross-depth loss with mean-square-root errors).
        edof_alpha: weight α of the EDoF loss's fidelity term (paper 0.3).
    """

    epochs: int = 1
    batch_size: int = 4
    micro_batches: int = 1
    max_steps: Optional[int] = None
    lr_lens: float = 1e-4
    lr_doe: float = 1e-1
    lr_network: float = 1e-4
    warmup_steps: int = 10
    min_lr_ratio: float = 0.0
    noise: bool = False
    read_noise: float = 2.0
    full_well: float = 10000.0
    loss: str = "l1"
    edof_alpha: float = 0.3


@dataclass
class TrainConfig:
    """A whole run (see the module docstring). ``dtype``: network and rendering precision ("float32" or
    "float64"; the optics is always float64). ``checkpoint_every``: optimizer steps between checkpoints.
    ``baseline``: "blank" (the same lens with a zero-phase DOE, same network training) or "paraxial" (a DOE
    designed with the paraxial wave model in ``baseline_steps`` Adam steps of the pre-stage objective, evaluated
    with the ray-wave model; :mod:`raywave.training.baselines`). ``baseline_reconstruction``: the model whose
    PSFs the baseline's reconstruction is built and trained with: "ray_wave" (the lens's true PSFs: the DOE alone
    is compared) or "paraxial" (the paper's protocol, supplement 2.6: a conventional paraxial pipeline, whose
    Wiener filters and network training use the paraxial model's PSFs, while its images are simulated with the
    ray-wave model). ``note``: printed when the run starts (what the config does on purpose)."""

    name: str = "run"
    seed: int = 0
    device: str = "cpu"
    dtype: str = "float32"
    lens: LensConfig = field(default_factory=LensConfig)
    optics: OpticsConfig = field(default_factory=OpticsConfig)
    data: DataConfig = field(default_factory=DataConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    pre_stage: PreStageConfig = field(default_factory=PreStageConfig)
    stage1: StageConfig = field(default_factory=StageConfig)
    stage2: StageConfig = field(default_factory=lambda: StageConfig(lr_doe=0.0, lr_lens=0.0, noise=True))
    checkpoint_every: int = 50
    baseline: str = "blank"
    baseline_steps: int = 50
    baseline_reconstruction: str = "ray_wave"
    #: a sentence the run prints when it starts (``raywave train``): what the config does on purpose that its
    #: warnings might otherwise make look like a fault (e.g. the aberration demo's DOE clipping its corner fields)
    note: str = ""


# ------------------------------------------------------------------ value rules
@dataclass(frozen=True)
class Rule:
    """What a numeric (or string) setting may hold, checked by :func:`from_dict` before anything runs.

    Attributes:
        lo, hi: bounds (None: unbounded); ``lo_open``: ``lo`` itself excluded (``> lo`` instead of ``>= lo``).
        inf: ``inf`` allowed (distances: a distant object); otherwise every number must be finite.
        length: exact list length (lists); ``nonempty``: a list or mapping must not be empty.
        choices: the allowed strings.
    """

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    inf: bool = False
    length: int | None = None
    nonempty: bool = False
    choices: tuple | None = None


_POS = Rule(lo=0, lo_open=True)  # > 0, finite
_NONNEG = Rule(lo=0)  # >= 0, finite
_COUNT = Rule(lo=1)  # integer >= 1
_UNIT = Rule(lo=0, hi=1)  # a fraction in [0, 1]

#: the rule of every numeric (and enumerated string) setting, by "Class.field"; a list's rule applies to each
#: entry (and its length). Every int / float / list field of the config dataclasses must be listed here
#: (tests/test_reliability_config.py checks it), so a new setting cannot slip in unchecked.
RULES: dict[str, Rule] = {
    "LensConfig.doe": Rule(choices=("pixel", "zernike", "file")),
    "LensConfig.doe_terms": _COUNT,
    "LensConfig.doe_pitch": _POS,
    "LensConfig.doe_size": _POS,
    "LensConfig.doe_distance": _NONNEG,
    "LensConfig.doe_after": _NONNEG,
    "LensConfig.focus_depth": Rule(lo=0, lo_open=True, inf=True),
    "LensConfig.sensor_pitch": _POS,
    "LensConfig.sensor_size": Rule(lo=0, lo_open=True, length=2),
    "OpticsConfig.grid": Rule(lo=1, length=2),
    "OpticsConfig.eval_grid": Rule(lo=1, length=2),
    "OpticsConfig.depths": Rule(lo=0, lo_open=True, inf=True, nonempty=True),
    "OpticsConfig.ks": _COUNT,
    "OpticsConfig.rays": Rule(lo=2),
    "OpticsConfig.wavelengths": Rule(lo=0, lo_open=True, hi=100.0, nonempty=True),
    "OpticsConfig.chunk": Rule(lo=1, choices=("auto",)),
    "OpticsConfig.field_jitter": _UNIT,
    "OpticsConfig.eval_ks": _COUNT,
    "OpticsConfig.doe_levels": Rule(lo=2),
    "OpticsConfig.doe_wavelength": Rule(lo=0, lo_open=True, hi=100.0),
    "OpticsConfig.fabricate_from": _NONNEG,
    "DataConfig.source": Rule(choices=("samples", "folder", "dead_leaves")),
    "DataConfig.patch_size": _COUNT,
    "DataConfig.patches_per_image": _COUNT,
    "DataConfig.eval_size": _COUNT,
    "DataConfig.dead_leaves_count": _COUNT,
    "NetworkConfig.kind": Rule(choices=("unet", "nafnet")),
    "NetworkConfig.deconv": Rule(choices=("none", "wiener", "wiener_select")),
    "NetworkConfig.width": _COUNT,
    "NetworkConfig.depth": _COUNT,
    "NetworkConfig.enc_blocks": Rule(lo=0, nonempty=True),
    "NetworkConfig.middle_blocks": _NONNEG,
    "NetworkConfig.wiener_lambda": _NONNEG,
    "NetworkConfig.wiener_mu": _NONNEG,
    "NetworkConfig.wiener_chroma": Rule(lo=0, lo_open=True, hi=1),
    "NetworkConfig.select_temperature": Rule(lo=0, lo_open=True),
    "PreStageConfig.steps": _NONNEG,
    "PreStageConfig.lr_doe": _NONNEG,
    "PreStageConfig.lr_lens": _NONNEG,
    "PreStageConfig.similarity_weight": _NONNEG,
    "PreStageConfig.restore_weight": _NONNEG,
    "PreStageConfig.restore_noise": _POS,
    "PreStageConfig.restore_filter": Rule(choices=("shared", "own")),
    "PreStageConfig.about": Rule(choices=("centroid", "center")),
    "StageConfig.epochs": _NONNEG,
    "StageConfig.batch_size": _COUNT,
    "StageConfig.micro_batches": _COUNT,
    "StageConfig.max_steps": _NONNEG,
    "StageConfig.lr_lens": _NONNEG,
    "StageConfig.lr_doe": _NONNEG,
    "StageConfig.lr_network": _NONNEG,
    "StageConfig.warmup_steps": _NONNEG,
    "StageConfig.min_lr_ratio": _UNIT,
    "StageConfig.read_noise": _NONNEG,
    "StageConfig.full_well": _POS,
    "StageConfig.loss": Rule(choices=("l1", "mse", "edof")),
    "StageConfig.edof_alpha": _UNIT,
    "TrainConfig.seed": _NONNEG,
    "TrainConfig.dtype": Rule(choices=("float32", "float64")),
    "TrainConfig.checkpoint_every": _COUNT,
    "TrainConfig.baseline": Rule(choices=("blank", "paraxial")),
    "TrainConfig.baseline_steps": _NONNEG,
    "TrainConfig.baseline_reconstruction": Rule(choices=("ray_wave", "paraxial")),
}


def _check_number(v, rule: Rule, where: str, source: str) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ConfigError(f"{source}: {where} must be a number, got {v!r}")
    if math.isnan(v) or (math.isinf(v) and not (rule.inf and v > 0)):
        allowed = "a finite number or inf" if rule.inf else "a finite number"
        raise ConfigError(f"{source}: {where} must be {allowed}, got {v!r}")
    if rule.lo is not None and (v <= rule.lo if rule.lo_open else v < rule.lo):
        raise ConfigError(f"{source}: {where} must be {'>' if rule.lo_open else '>='} {rule.lo:g}, got {v!r}")
    if rule.hi is not None and v > rule.hi:
        raise ConfigError(f"{source}: {where} must be <= {rule.hi:g}, got {v!r}")


def _check_rule(cls, name: str, value, tp, where: str, source: str) -> None:
    """Check a converted ``value`` of field ``cls.name`` against :data:`RULES` (every float finite by default)."""
    rule = RULES.get(f"{cls.__name__}.{name}")
    if value is None:
        return
    if rule is None:
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"{source}: {where} must be a finite number, got {value!r}")
        return
    if isinstance(value, str):
        if rule.choices is not None and value not in rule.choices:
            raise ConfigError(f"{source}: {where} must be one of {', '.join(map(repr, rule.choices))}, got {value!r}")
        return
    if isinstance(value, (list, tuple)):
        if rule.length is not None and len(value) != rule.length:
            raise ConfigError(f"{source}: {where} must have {rule.length} entries, got {len(value)}")
        if rule.nonempty and not value:
            raise ConfigError(f"{source}: {where} must not be empty")
        integer = cls.__name__ in ("OpticsConfig", "NetworkConfig") and name in ("grid", "eval_grid", "enc_blocks")
        for i, v in enumerate(value):
            if integer and (isinstance(v, bool) or not isinstance(v, int)):
                raise ConfigError(f"{source}: {where}[{i}] must be an integer, got {v!r}")
            _check_number(v, rule, f"{where}[{i}]", source)
        return
    if isinstance(value, dict):
        if rule.nonempty and not value:
            raise ConfigError(f"{source}: {where} must not be empty")
        for k, vs in value.items():
            vs = vs if isinstance(vs, list) else [vs]
            if rule.nonempty and not vs:
                raise ConfigError(f"{source}: {where}.{k} must not be empty")
            for i, v in enumerate(vs):
                _check_number(v, rule, f"{where}.{k}[{i}]", source)
        return
    _check_number(value, rule, where, source)


# ------------------------------------------------------------------ dict ↔ dataclass
def _check_value(value, tp, where: str, source: str):
    """Validate (and lightly coerce: int → float, 'inf' → inf) ``value`` against the annotation ``tp``."""
    origin = typing.get_origin(tp)
    if origin in (Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _check_value(value, a, where, source)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(errors[0] if errors else f"{source}: {where}: invalid value {value!r}")
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{source}: {where} must be a mapping, got {value!r}")
        return from_dict(tp, value, source, where)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{source}: {where} must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{source}: {where} must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, str) and value.strip().lower() in ("inf", "+inf", "infinity"):
            return math.inf
        if isinstance(value, str):  # PyYAML reads 1e-3 (no dot) as a string: accept what float() reads
            try:
                value = float(value.strip())
            except ValueError:
                raise ConfigError(f"{source}: {where} must be a number, got {value!r}") from None
            if not math.isfinite(value):
                raise ConfigError(f"{source}: {where} must be a finite number or inf, got {value!r}")
            return value
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{source}: {where} must be a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{source}: {where} must be a string, got {value!r}")
        return value
    if tp is list or origin is list:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{source}: {where} must be a list, got {value!r}")
        return [_inf(v) for v in value]
    if tp is dict or origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{source}: {where} must be a mapping, got {value!r}")
        return {k: [_inf(x) for x in v] if isinstance(v, list) else _inf(v) for k, v in value.items()}
    return value


def _inf(v):
    if isinstance(v, str) and v.strip().lower() in ("inf", "+inf", "infinity"):
        return math.inf
    return v


def from_dict(cls, data: dict, source: str = "<dict>", prefix: str = ""):
    """Build dataclass ``cls`` from a (nested) dict; unknown keys and wrongly typed values are
    :class:`ConfigError` naming ``source`` and the dotted key."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: {prefix or 'the config'} must be a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        where = f"{prefix}.{key}" if prefix else str(key)
        if key not in names:
            raise ConfigError(f"{source}: unknown key {where!r} (known keys{' of ' + prefix if prefix else ''}: "
                              f"{', '.join(sorted(names))})")
        kwargs[key] = _check_value(value, hints[key], where, source)
        _check_rule(cls, key, kwargs[key], hints[key], where, source)
    return cls(**kwargs)


def to_dict(cfg) -> dict[str, Any]:
    """The config as plain dicts/lists (every field), for YAML/JSON."""
    return dataclasses.asdict(cfg)


def _yaml_safe(x):
    if isinstance(x, float) and math.isinf(x):
        return x  # PyYAML writes .inf / -.inf and reads them back
    if isinstance(x, dict):
        return {k: _yaml_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_yaml_safe(v) for v in x]
    return x


def load_config(path) -> TrainConfig:
    """Read a YAML config (missing keys: defaults; unknown keys: :class:`ConfigError` naming key and file)."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:  # one line: file:line: the problem
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{where}: not valid YAML: {problem}") from None
    if data is None:
        raise ConfigError(f"{path}: the config file is empty (write at least one setting, e.g. 'name: run'; "
                          "see configs/*.yaml)")
    return from_dict(TrainConfig, data, str(path))


def dump_config(cfg: TrainConfig, path=None) -> str:
    """The resolved config as YAML text (written to ``path`` if given)."""
    import yaml

    text = yaml.safe_dump(_yaml_safe(to_dict(cfg)), sort_keys=False, default_flow_style=None)
    if path is not None:
        Path(path).write_text(text, encoding="utf-8")
    return text


def apply_overrides(cfg: TrainConfig, overrides, source: str = "--set") -> TrainConfig:
    """Return a copy of ``cfg`` with ``overrides`` applied: strings ``"dotted.key=value"`` (the value is read as
    YAML: ``data.root=/data/DIV2K``, ``optics.grid=[5, 5]``, ``stage1.max_steps=10``, ``optics.depths=[.inf]``).
    An unknown key, a key that names a whole section, or a wrongly typed value is a :class:`ConfigError` that
    names the override."""
    import yaml

    data = to_dict(cfg)
    for item in overrides or ():
        key, sep, text = str(item).partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"{source} {item!r}: expected KEY=VALUE, e.g. data.root=/data/DIV2K")
        try:
            value = yaml.safe_load(text) if text.strip() else None
        except yaml.YAMLError as exc:
            raise ConfigError(f"{source} {item!r}: the value is not valid YAML: {exc}") from exc
        node, obj, parts = data, cfg, key.split(".")
        for i, part in enumerate(parts):
            if not dataclasses.is_dataclass(obj) or part not in node:
                where = ".".join(parts[:i + 1])
                known = ", ".join(sorted(node)) if dataclasses.is_dataclass(obj) else "none"
                raise ConfigError(f"{source} {item!r}: unknown key {where!r} (known keys here: {known})")
            obj = getattr(obj, part)
            if i < len(parts) - 1:
                node = node[part]
        if dataclasses.is_dataclass(obj):
            raise ConfigError(f"{source} {item!r}: {key!r} is a section; set one of its keys "
                              f"({', '.join(sorted(node[parts[-1]]))})")
        node[parts[-1]] = value
    return from_dict(TrainConfig, data, source)
