"""The ``train`` and ``eval`` commands: end-to-end design runs.

    raywave train CONFIG.yaml [-o RUN_DIR] [--set KEY=VALUE ...] [--no-baseline] [--restart | --resume]
                  [--max-steps N] [--nproc N] [--quiet]
    raywave eval RUN_DIR [--no-noise] [--quiet]

``train`` runs (or resumes, from the run folder's latest checkpoint) the stages of CONFIG (see
:mod:`raywave.training.trainer`), then the baseline (config ``baseline``: the same lens with a blank DOE, or with
a DOE designed with the paraxial wave model; the same network training) in ``RUN_DIR/baseline``, evaluates both
on the held-out images and writes into RUN_DIR: ``config.yaml``,
``checkpoints/``, ``log.jsonl``, ``metrics.json`` (PSNR/SSIM per depth and field zone, designed vs baseline),
``final/`` (lens JSON + DOE phase, ``doe.pt``, the fabrication masks of ``optics.doe_levels`` levels) and
``figures/`` (loss curves, PSF maps before/after, sample reconstructions). RUN_DIR defaults to ``runs/<config name>``. ``--max-steps N`` caps every
stage at N optimizer steps (a quick look). ``--set KEY=VALUE`` (repeatable) overrides a config key, e.g.
``--set data.root=/data/DIV2K`` (the value is YAML; unknown keys are errors). ``--nproc N`` trains on N local
gloo processes (the steps of one process, split: :mod:`raywave.training.parallel`); under ``torchrun`` the ranks train together and rank 0
evaluates. ``eval`` re-evaluates a finished run folder.

A run folder that holds checkpoints of another config (its ``config.yaml`` differs from CONFIG with its
``--set`` and ``--max-steps``) is refused unless ``--resume`` (continue with the new settings; config.yaml is
replaced and the changes printed) or ``--restart`` (its checkpoints and logs are removed); a run that continues
prints "resuming from step N".
"""

from __future__ import annotations

import json
import os
import re
import shutil
import sys
from pathlib import Path

from raywave.cli.errors import CommandError, integer_arg as _integer, json_dumps

__all__ = ["register"]


def register(subparsers) -> None:
    p = subparsers.add_parser("train", help="end-to-end design: train lens/DOE + network from a YAML config",
                              description=plain_text(" ".join(__doc__.split("\n\n")[2:4])))
    p.add_argument("config", help="YAML config (configs/*.yaml)")
    p.add_argument("-o", "--output", help="run folder (default runs/<config name>)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key (repeatable; the value is YAML), e.g. --set data.root=/data/DIV2K")
    p.add_argument("--no-baseline", action="store_true", help="skip the baseline (config key baseline)")
    p.add_argument("--nproc", default=None, metavar="N", help="train on N local gloo processes (CPU)")
    p.add_argument("--restart", action="store_true",
                   help="start the run folder over: its checkpoints and logs are removed (needed, or --resume, when "
                        "the config differs from the folder's config.yaml)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run folder's latest checkpoint with this config even where it differs from the "
                        "folder's config.yaml (which is then replaced; the changes are printed)")
    p.add_argument("--max-steps", default=None, metavar="N", help="cap every stage at N optimizer steps")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_train)
    e = subparsers.add_parser("eval", help="evaluate a training run folder (metrics and figures)")
    e.add_argument("run_dir", help="run folder written by raywave train")
    e.add_argument("--no-noise", action="store_true", help="evaluate without sensor noise")
    e.add_argument("--quiet", action="store_true", help="no progress bars")
    e.set_defaults(func=_eval)


def _load(path, overrides=()):
    from raywave.training.config import ConfigError, apply_overrides, load_config

    try:
        cfg = load_config(path)
        return apply_overrides(cfg, overrides) if overrides else cfg
    except ConfigError as err:
        raise CommandError(str(err)) from None


def _cap(cfg, n: int | None):
    if n is None:
        return cfg
    cfg.pre_stage.steps = min(cfg.pre_stage.steps, n)
    for sc in (cfg.stage1, cfg.stage2):
        sc.max_steps = n if sc.max_steps is None else min(sc.max_steps, n)
    return cfg


def plain_text(doc: str) -> str:
    """A docstring without its Sphinx markup (for ``--help``): ``:mod:`x``` -> ``x``, double back-quotes
    dropped."""
    doc = re.sub(r":[a-z]+:`~?([^`]+)`", r"\1", doc)
    return doc.replace("``", "")


#: config keys that do not change what a run trains (a changed note is no reason to refuse a folder)
IGNORED_KEYS = ("note",)


def config_changes(old, new, prefix: str = "") -> list[str]:
    """``"key: old -> new"`` for every setting that differs between two configs (dataclasses or dicts), leaving
    out :data:`IGNORED_KEYS`."""
    from raywave.training.config import to_dict

    a = old if isinstance(old, dict) else to_dict(old)
    b = new if isinstance(new, dict) else to_dict(new)
    out = []
    for k in sorted(set(a) | set(b)):
        if not prefix and k in IGNORED_KEYS:
            continue
        va, vb = a.get(k), b.get(k)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += config_changes(va, vb, f"{prefix}{k}.")
        elif va != vb:
            out.append(f"{prefix}{k}: {va!r} -> {vb!r}")
    return out


#: what ``--restart`` removes from a run folder and its sub-runs (the run's state; figures and exports are rewritten)
RUN_STATE = ("checkpoints", "log.jsonl", "warnings.jsonl")
SUB_RUNS = ("", "baseline", "plain_network", "baseline/plain_network")


def _clear_run(run_dir: Path) -> bool:
    """Remove the run state (:data:`RUN_STATE`) of ``run_dir`` and its sub-runs; True if anything was removed."""
    removed = False
    for sub in SUB_RUNS:
        for name in RUN_STATE:
            p = run_dir / sub / name
            if p.is_dir():
                shutil.rmtree(p)
                removed = True
            elif p.is_file():
                p.unlink()
                removed = True
    return removed


def resume_position(run_dir: Path) -> tuple[int, str, int] | None:
    """``(global step, stage, stage step)`` of the run folder's latest checkpoint, or None when it has none."""
    import torch

    from raywave.training.checkpoint import latest_checkpoint

    ck = latest_checkpoint(run_dir)
    if ck is None:
        return None
    extra = torch.load(ck, map_location="cpu", weights_only=True).get("extra", {})
    step = int(re.fullmatch(r"step_(\d+)\.pt", ck.name).group(1))
    return step, str(extra.get("stage", "?")), int(extra.get("stage_step", 0))


def prepare_run_folder(run_dir: Path, cfg, restart: bool, resume: bool) -> list[str]:
    """Check ``cfg`` against the run folder's ``config.yaml`` before anything is written, and return the lines to
    print. A folder with checkpoints whose config differs is a :class:`CommandError` (naming the changed keys)
    unless ``restart`` (the run state is removed, :data:`RUN_STATE`) or ``resume`` (the run continues with the
    new settings, which replace config.yaml); config.yaml is never replaced silently. A run that continues says
    from which step."""
    from raywave.training.config import ConfigError, load_config

    if restart and resume:
        raise CommandError("--restart and --resume exclude each other")
    lines = []
    cfg_path = run_dir / "config.yaml"
    pos = resume_position(run_dir)
    if restart:
        if _clear_run(run_dir):
            lines.append(f"restarting {run_dir}: the previous run's checkpoints and logs were removed")
        return lines
    if cfg_path.is_file():
        try:
            changes = config_changes(load_config(cfg_path), cfg)
        except ConfigError as e:
            changes = [f"the folder's config.yaml does not load ({e})"]
        if changes and pos is not None and not resume:
            shown = "; ".join(changes[:6]) + (f"; … ({len(changes)} in all)" if len(changes) > 6 else "")
            raise CommandError(f"{run_dir} holds a run of another config ({shown}): give --resume to continue it "
                               "with these settings, --restart to start it over, or another folder (-o)")
        if changes:
            why = "continuing with the new settings" if pos is not None else "nothing was trained yet"
            lines.append(f"{cfg_path} replaced ({why}): " + "; ".join(changes))
    if pos is not None:
        step, stage, stage_step = pos
        if stage == "done":
            lines.append(f"{run_dir}: the run is finished ({step} steps): evaluating it again")
        else:
            lines.append(f"resuming from step {step} ({stage} step {stage_step}) of {run_dir}")
    return lines


def _train(args) -> int:
    from raywave.training.trainer import Trainer

    cfg = _load(args.config, args.overrides)
    cap = _integer(args.max_steps, "--max-steps", minimum=0) if args.max_steps is not None else None
    cfg = _cap(cfg, cap)
    run_dir = Path(args.output) if args.output else Path("runs") / cfg.name
    for line in prepare_run_folder(run_dir, cfg, args.restart, getattr(args, "resume", False)):
        print(line, file=sys.stderr)
    if cfg.note:
        print("note: " + " ".join(cfg.note.split()), file=sys.stderr)
    nproc = _integer(args.nproc, "--nproc", minimum=1) if args.nproc is not None else 1
    if nproc > 1 or int(os.environ.get("WORLD_SIZE", "1")) > 1:
        return _train_parallel(args, cfg, run_dir, nproc)
    designed = Trainer(cfg, run_dir, progress=not args.quiet)
    designed.run(resume=not args.restart)
    trainers = {"designed": designed}
    if not args.no_baseline:
        # the same frozen lens: the baseline reuses the designed run's DOE-plane fields
        base = Trainer(cfg, run_dir / "baseline", baseline=True, progress=not args.quiet, field_cache=designed.cache)
        base.run(resume=not args.restart)
        trainers["baseline"] = base
    if cfg.network.ablation:
        for t in trainers.values():
            t.train_plain_network()
    designed.export()
    _report(run_dir, trainers, noise=True)
    return 0


def _train_parallel(args, cfg, run_dir: Path, nproc: int) -> int:
    """Train on ``nproc`` spawned gloo processes (or the ranks of torchrun), then evaluate and export in this
    process (rank 0 under torchrun) from the final checkpoints."""
    import torch.distributed as dist

    from raywave.training.parallel import init_from_env, rank_and_world, spawn, train_ranks
    from raywave.training.trainer import Trainer

    resume, baseline = not args.restart, not args.no_baseline
    if nproc > 1 and int(os.environ.get("WORLD_SIZE", "1")) > 1:
        raise CommandError("--nproc: torchrun already started the processes (WORLD_SIZE is set); drop --nproc")
    if nproc > 1:
        spawn(nproc, train_ranks, cfg, str(run_dir), resume, baseline, not args.quiet)
    else:
        init_from_env()
        train_ranks(cfg, run_dir, resume, baseline, not args.quiet)
        rank, _ = rank_and_world()
        dist.barrier()
        dist.destroy_process_group()
        if rank != 0:
            return 0
    trainers = {"designed": Trainer(cfg, run_dir, progress=not args.quiet)}
    if baseline:
        trainers["baseline"] = Trainer(cfg, run_dir / "baseline", baseline=True, progress=not args.quiet,
                                       field_cache=trainers["designed"].cache)
    for t in trainers.values():
        t.restore()
        if cfg.network.ablation:
            t.train_plain_network()
    trainers["designed"].export()
    _report(run_dir, trainers, noise=True)
    return 0


def _eval(args) -> int:
    from raywave.training.checkpoint import latest_checkpoint
    from raywave.training.trainer import Trainer

    run_dir = Path(args.run_dir)
    if not (run_dir / "config.yaml").is_file():
        raise CommandError(f"{run_dir} is not a run folder (no config.yaml)")
    cfg = _load(run_dir / "config.yaml")
    trainers, shared = {}, None
    for name, folder, baseline in (("designed", run_dir, False), ("baseline", run_dir / "baseline", True)):
        if latest_checkpoint(folder) is None:
            if name == "designed":
                raise CommandError(f"{run_dir}: no checkpoint to evaluate")
            continue
        t = Trainer(cfg, folder, baseline=baseline, progress=not args.quiet, field_cache=shared)
        shared = t.cache
        t.restore()
        if cfg.network.ablation and latest_checkpoint(folder / "plain_network") is not None:
            t.train_plain_network()  # finished: restores the plain network (nothing left to train)
        trainers[name] = t
    _report(run_dir, trainers, noise=not args.no_noise)
    return 0


#: the ablation table's reconstructions: metrics.json suffix → row label
ABLATION_ROWS = {"_input": "sensor image", "_network_only": "network only", "_deconv": "deconvolution only",
                 "_deconv_true": "deconvolution only, true PSFs", "": "reconstruction"}


def ablation_table(metrics: dict) -> dict:
    """``{doe: {reconstruction: {zone key: {"psnr", "ssim"}}}}`` from the metrics of each trainer (the rows
    present: sensor image, network only, deconvolution only, the trained reconstruction)."""
    table = {}
    for name in ("baseline", "designed"):
        if name not in metrics:
            continue
        m = metrics[name]
        rows = {}
        for suffix, label in ABLATION_ROWS.items():
            if f"psnr{suffix}" not in m["mean"]:
                continue
            rows[label] = {k: {"psnr": v[f"psnr{suffix}"], "ssim": v[f"ssim{suffix}"]} for k, v in m.items()}
        table[name] = rows
    return table


def format_ablation(table: dict, deconv: str) -> str:
    """The ablation table as Markdown: rows = DOE × reconstruction, columns = zones (PSNR dB / SSIM)."""
    zones = None
    lines = []
    for doe, rows in table.items():
        for label, cols in rows.items():
            if zones is None:
                zones = list(cols)
                lines.append("| DOE | reconstruction | " + " | ".join(zones) + " |")
                lines.append("|---|---|" + "---|" * len(zones))
            name = "deconvolution + network" if (label == "reconstruction" and deconv.startswith("wiener")) else \
                ("network" if label == "reconstruction" else label)
            lines.append(f"| {doe} | {name} | " + " | ".join(f"{cols[z]['psnr']:.2f} / {cols[z]['ssim']:.3f}"
                                                              for z in zones) + " |")
    return "\n".join(lines)


def _report(run_dir: Path, trainers: dict, noise: bool) -> None:
    metrics = {name: t.evaluate(noise=noise) for name, t in trainers.items()}
    if "baseline" in metrics:
        metrics["gain_db"] = {k: metrics["designed"][k]["psnr"] - metrics["baseline"][k]["psnr"]
                              for k in metrics["designed"]}
    deconv = next(iter(trainers.values())).cfg.network.deconv
    metrics["ablation"] = ablation_table(metrics)
    (run_dir / "metrics.json").write_text(json_dumps(metrics, indent=2) + "\n")
    (run_dir / "ablation.md").write_text("PSNR (dB) / SSIM on the held-out images\n\n"
                                         + format_ablation(metrics["ablation"], deconv) + "\n")
    _figures(run_dir, trainers)
    m = metrics["designed"]["mean"]
    line = f"designed: PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f} (sensor image {m['psnr_input']:.2f} dB)"
    if "baseline" in metrics:
        b = metrics["baseline"]["mean"]
        line += f"; baseline: PSNR {b['psnr']:.2f} dB, SSIM {b['ssim']:.4f} (sensor image {b['psnr_input']:.2f} dB)"
    print(line)
    print(format_ablation(metrics["ablation"], deconv))
    print(f"run folder: {run_dir}")


def _figures(run_dir: Path, trainers: dict) -> None:
    """``run_dir/figures``: loss curves, PSF maps per depth and sample reconstructions of every trainer."""
    fig_dir = run_dir / "figures"
    _loss_figure(fig_dir, trainers)
    _psf_map_figures(fig_dir, trainers)
    _reconstruction_figures(fig_dir, trainers)


def _loss_figure(fig_dir: Path, trainers: dict) -> None:
    """``loss.png``: the loss per step of every trainer's stages (pre, stage1, stage2), log scale, with its running
    mean."""
    from raywave.plotting._mpl import plt, save

    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    for name, t in trainers.items():
        if not t.log_path.is_file():
            continue
        recs = [json.loads(line) for line in t.log_path.read_text().splitlines() if line.strip()]
        for stage in ("pre", "stage1", "stage2"):
            ys = [r["loss"] for r in recs if r.get("stage") == stage and "loss" in r]
            if ys:
                steps = range(1, len(ys) + 1)
                raw, = ax.plot(steps, ys, alpha=0.25, lw=0.8)  # per-step: noisy (random patches, depths, noise)
                ax.plot(steps, _running_mean(ys, max(3, len(ys) // 20)), color=raw.get_color(), lw=1.5,
                        label=f"{name} {stage}")
    ax.set_xlabel("step"), ax.set_ylabel("loss"), ax.set_yscale("log"), ax.legend(fontsize=7)
    ax.set_title("faint: per step; solid: running mean over 5 % of the stage's steps (at least 3)", fontsize=8)
    save(fig, fig_dir / "loss.png")


def _running_mean(ys: list, width: int) -> list:
    """The mean of each value with the up to ``width − 1`` values before it (as many as there are at the start)."""
    out, acc = [], 0.0
    for i, y in enumerate(ys):
        acc += y - (ys[i - width] if i >= width else 0.0)
        out.append(acc / min(i + 1, width))
    return out


def _psf_map_figures(fig_dir: Path, trainers: dict) -> None:
    """``psf_map_depth<d>.png``: per object depth (mm) the evaluation PSF maps of the trainers side by side
    (mosaic of the PSFs, √ scale, normalised per channel)."""
    from raywave.plotting._mpl import plt, save

    maps = {name: t.truth_map() for name, t in trainers.items() if t.stage2_map is not None}  # what the lens does
    for d, depth in enumerate(next(iter(trainers.values())).depths):
        fig, axes = plt.subplots(1, len(maps), figsize=(5 * len(maps), 5), constrained_layout=True, squeeze=False)
        for ax, (name, pm) in zip(axes[0], maps.items()):
            psf = pm.psf[d]  # (3, N, M, ks, ks)
            C, N, M, ks, _ = psf.shape
            mosaic = psf.permute(1, 3, 2, 4, 0).reshape(N * ks, M * ks, C)
            mosaic = mosaic / mosaic.amax(dim=(0, 1), keepdim=True).clamp_min(1e-30)
            ax.imshow(mosaic.clamp(0, 1).sqrt().numpy(), origin="lower")
            ax.set_title(f"{name}: PSF map at {depth:g} mm (√, per-channel max)")
            ax.set_xticks([]), ax.set_yticks([])
        save(fig, fig_dir / f"psf_map_depth{d}.png")


def _reconstruction_row(name: str, t, d: int, uv) -> list:
    """One figure row: the trainer's first held-out image, its simulated sensor image at depth index ``d`` and
    sensor zone ``uv`` (with noise, a fixed seed) and the restored image, as (title, image) pairs."""
    import torch

    from raywave.imaging.render import render
    from raywave.training.metrics import psnr

    img = t.eval_images_tensor()[:1]
    pm, truth = t.stage2_map, t.truth_map()  # the reconstruction's map; the lens's own (the sensor image)
    ext = t._extent(img.shape[-2:], uv)
    with torch.no_grad():
        sim = render(img, truth.psf[d], positions=truth.positions, centers=truth.centers[d],
                     sensor_size=truth.sensor_size, pitch=truth.pitch, extent=ext)
        sim = t._sensor()(sim, generator=torch.Generator().manual_seed(12345)).clamp(0, 1)
        rec = t.reconstruct(sim, pm.psf, pm.centers, [ext], pm.positions).clamp(0, 1)
    return [("ground truth", img[0]),
            (f"{name}: sensor image {float(psnr(sim.double(), img.double())):.2f} dB", sim[0]),
            (f"{name}: restored {float(psnr(rec.double(), img.double())):.2f} dB", rec[0])]


def _reconstruction_figures(fig_dir: Path, trainers: dict) -> None:
    """``reconstructions_<zone>[_depth<d>].png``: per zone (centre, edge) and depth, the first held-out image as
    evaluated (noise), one row per trainer."""
    from raywave.imaging.data import linear_to_srgb
    from raywave.plotting._mpl import plt, save

    first = next(iter(trainers.values()))
    zones = {"centre": (0.0, 0.0), "edge": (0.8, 0.8)}
    for d, depth in enumerate(first.depths):
        for zone, uv in zones.items():
            rows = [_reconstruction_row(name, t, d, uv) for name, t in trainers.items()]
            fig, axes = plt.subplots(len(rows), 3, figsize=(9.6, 3.4 * len(rows)), constrained_layout=True,
                                     squeeze=False)
            for r, row in enumerate(rows):
                for ax, (title, im) in zip(axes[r], row):
                    ax.imshow(linear_to_srgb(im.double().clamp(0, 1)).permute(1, 2, 0).numpy())
                    ax.set_title(title, fontsize=8), ax.set_xticks([]), ax.set_yticks([])
            fig.suptitle(f"{zone} of the sensor, object at {depth:g} mm", fontsize=9)
            suffix = f"_depth{d}" if len(first.depths) > 1 else ""
            save(fig, fig_dir / f"reconstructions_{zone}{suffix}.png")
