"""One optimizer iteration per stage of a :class:`~raywave.training.trainer.Trainer` (pre-stage, stage 1,
stage 2) and the hooks through which :class:`~raywave.training.parallel.DistributedTrainer` splits the work over
processes. A mixin: it reads the Trainer's configuration, data, optics and network."""

from __future__ import annotations

import torch

from raywave.training.baselines import objective_settings, psf_objective
from raywave.training.losses import edof_loss, image_loss
from raywave.training.replay import OpticsStep

__all__ = ["StageSteps"]


#: redraws of a patch's place before a dark-node map gives up (then the last draw stands)
_LIT_DRAWS = 64


class DarkRegionWarning(UserWarning):
    """Some nodes of a training PSF map receive no light: training patches avoid them."""


def _lit_nodes(pm):
    """(N, M) bool of the map's nodes whose PSFs carry light at every depth and wavelength, or None when all do
    (or no map is given). ``pm``: a map (its ``psf``) or the PSFs ``(..., N, M, ks, ks)`` themselves. A map with no
    lit node at all is an error."""
    if pm is None:
        return None
    psf = pm if torch.is_tensor(pm) else pm.psf
    lit = (psf.detach().sum(dim=(-1, -2)) > 0).flatten(0, -3).all(0)  # (N, M)
    if bool(lit.all()):
        return None
    if not bool(lit.any()):
        raise ValueError("no node of the PSF map receives light (the DOE aperture or vignetting blocks every beam): "
                         "check lens.doe_size, lens.doe_distance and the lens file's apertures")
    return lit.cpu()


def _nearest_node(positions: torch.Tensor, uv: torch.Tensor) -> tuple[int, int]:
    """(i, j) of the node of ``positions`` (N, M, 2) (normalised sensor coordinates) nearest to ``uv`` (2,)."""
    d = (positions.detach().cpu().to(torch.float64) - uv).square().sum(-1)
    k = int(torch.argmin(d))
    return k // d.shape[1], k % d.shape[1]


class StageSteps:
    """The per-stage iterations and the multi-process hooks (mixin of :class:`~raywave.training.trainer.Trainer`)."""

    # ------------------------------------------------------------------ hooks (one process: trivial; several:
    # raywave.training.parallel.DistributedTrainer splits the work and sums the gradients through these)
    def _parts(self, batch: int, micro: int, loss: str) -> list:
        """The index sets (micro-batches) of a batch of ``batch`` images that this process renders."""
        return list(torch.arange(batch, device="cpu").chunk(max(1, min(int(micro), batch))))

    def _replay(self, step: OpticsStep, leaf_grads_partial: bool) -> None:
        """Replay ``step``'s chunks with autograd (``leaf_grads_partial``: ∂L/∂PSF holds this process's share
        of the batch only)."""
        step.backward()

    def _sync_grads(self) -> None:
        """Make the parameters' gradients those of the whole step (one process: they are)."""

    def _sum(self, value: float) -> float:
        """The step's loss from this process's share (one process: the loss itself)."""
        return value

    def _optimizer_step(self, opt, sched) -> None:
        self._sync_grads()
        self._check_grads(opt)
        opt.step(), sched.step(), opt.zero_grad(set_to_none=True)

    def _check_grads(self, opt) -> None:
        """Refuse a non-finite gradient before it reaches the parameters (Adam would spread the NaN into the
        DOE / lens / network, and the next PSF would fail far from the cause); names the parameter."""
        names = {id(p): n for n, p in self._named_parameters()}
        for group in opt.param_groups:
            for p in group["params"]:
                if p.grad is not None and not bool(torch.isfinite(p.grad).all()):
                    raise FloatingPointError(f"the gradient of {names.get(id(p), 'a parameter')} "
                                             f"{tuple(p.shape)} is not finite (NaN or inf); nothing was updated")

    def _named_parameters(self):
        for key, module in self._modules().items():
            for n, p in module.named_parameters():
                yield f"{key}.{n}", p

    # ------------------------------------------------------------------ one iteration per stage
    def _pre_step(self, opt, sched) -> float:
        pc = self.cfg.pre_stage
        fields, _ = self.step_nodes()
        step = self.optics_step(fields)
        psf, cen = step.leaves()
        p, _ = self._as_map(psf, cen)
        loss = psf_objective(p, **objective_settings(pc))
        loss.backward()  # the whole map's ∂L/∂PSF (the same in every process)
        self._replay(step, leaf_grads_partial=False)
        self._optimizer_step(opt, sched)
        return float(loss.detach())

    def _stage1_step(self, step_idx, opt, sched) -> float:
        sc = self.cfg.stage1
        img = self._batch("stage1", step_idx)
        places = [self._random_uv() for _ in range(img.shape[0])]  # drawn first: the stream of a fully lit map
        fields, positions = self.step_nodes()
        ostep = self.optics_step(fields)
        frozen = not any(p.requires_grad for p in self.hl.parameters())
        if frozen and float(self.cfg.optics.field_jitter) > 0:
            psf, cen = (t.detach() for t in ostep.forward())  # the nodes move every step: nothing to memoise
        elif frozen:
            psf, cen = self._frozen_map(fields, ostep.draws)
        elif self.cfg.optics.replay:
            psf, cen = ostep.leaves()
        else:
            psf, cen = ostep.full_graph()
        p, c = self._as_map(psf, cen)
        lit = _lit_nodes(p)  # this step's map: a patch whose nearest node is dark is drawn again
        extents = [self._extent(img.shape[-2:], self._lit_uv(uv, positions, lit)) for uv in places]
        B = img.shape[0]
        parts = self._parts(B, sc.micro_batches, sc.loss)
        total = 0.0
        for j, idx in enumerate(parts):
            loss = self._recon_loss(img[idx], p, c, [extents[i] for i in idx.tolist()], sc,
                                    positions=positions) * (len(idx) / B)
            loss.backward(retain_graph=not (self.cfg.optics.replay or frozen) and j < len(parts) - 1)
            total += float(loss.detach())
        if self.cfg.optics.replay and not frozen:
            self._replay(ostep, leaf_grads_partial=True)
        self._optimizer_step(opt, sched)
        return self._sum(total)

    def _frozen_map(self, fields, draws):
        """The step's map ``(psf, centres)`` when nothing optical trains (a baseline) and the nodes stay put: the
        PSFs of every wavelength of the colour table are computed once, as one map, and each step picks its
        draw's (a channel's PSFs depend on its own wavelength only). Detached."""
        table = self.color.wavelength_table()  # (C, K)
        if "all" not in self._frozen_maps:
            step = self.optics_step(fields, wavelengths=table.reshape(-1))
            self._frozen_maps["all"] = tuple(t.detach() for t in step.forward())  # (D·F, C·K, ...)
        psf, cen = self._frozen_maps["all"]
        C, K = table.shape
        d = torch.as_tensor(draws, dtype=torch.float64, device="cpu").reshape(C, 1)
        idx = [c * K + int((table[c] - d[c]).abs().argmin()) for c in range(C)]
        return psf[:, idx], cen[:, idx]

    def _recon_loss(self, img, p, c, extents, sc, noise=None, positions=None):
        recon = []
        for d in range(p.shape[0]):
            sims = torch.cat([self.simulate(img[i:i + 1], p[d], c[d], extents[i], positions)
                              for i in range(img.shape[0])])
            if noise is not None:
                sims = noise(sims, generator=self.gen)
            recon.append(self.reconstruct(sims, p, c, extents, positions))
        if sc.loss == "edof":
            return edof_loss(recon, img, alpha=sc.edof_alpha)
        return sum(self.loss_fn(r, img) for r in recon) / len(recon)

    def _stage2_step(self, step_idx, opt, sched) -> float:
        sc = self.cfg.stage2
        if self.stage2_map is None:
            self.stage2_map = self.evaluation_map()
        pm, sensor = self.stage2_map, self._sensor() if sc.noise else None
        img = self._batch("stage2", step_idx)
        lit = _lit_nodes(pm)  # once per step: the map's lit nodes
        extents = [self._extent(img.shape[-2:], self._lit_uv(self._random_uv(), pm.positions, lit))
                   for _ in range(img.shape[0])]
        loss = self._recon_loss_map(img, pm, extents, sc, sensor)
        loss.backward()
        self._optimizer_step(opt, sched)
        return self._sum(float(loss.detach()))

    def _recon_loss_map(self, img, pm, extents, sc, sensor):
        from raywave.imaging.render import render

        recon = []
        for d in range(pm.psf.shape[0]):
            sims = torch.cat([render(img[i:i + 1], pm.psf[d], positions=pm.positions, centers=pm.centers[d],
                                     sensor_size=pm.sensor_size, pitch=pm.pitch, extent=extents[i])
                              for i in range(img.shape[0])])
            if sensor is not None:
                sims = sensor(sims, generator=self.gen)
            recon.append(self.reconstruct(sims, pm.psf, pm.centers, extents, pm.positions))
        if sc.loss == "edof":
            return edof_loss(recon, img, alpha=sc.edof_alpha)
        return sum(image_loss(sc.loss)(r, img) for r in recon) / len(recon)
