"""The fabrication-aware DOE schedule of a :class:`~raywave.training.trainer.Trainer` (``optics.doe_levels``,
``doe_wavelength``, ``doe_material``, ``fabricate_from``): the DOE is trained as the continuous height map in its
material, then as the wrapped L-level element (straight-through gradient) from a stage-1 step on; stage 2, the
evaluation and the export use the quantised element. A mixin: it reads the Trainer's ``cfg``, ``hl``,
``_frozen_maps`` and ``stage2_map``."""

from __future__ import annotations

from raywave.doe.base import check_levels

__all__ = ["FabricationSchedule"]


class FabricationSchedule:
    """The fabrication state of the Trainer's DOE per stage and step (mixin of
    :class:`~raywave.training.trainer.Trainer`)."""

    def _init_fabrication(self) -> None:
        """``optics.doe_levels / doe_wavelength / doe_material``: make the DOE the continuous (unwrapped) height
        map in its material now; :meth:`_fabrication` quantises it from ``optics.fabricate_from`` on."""
        oc = self.cfg.optics
        self.fab_levels = None if oc.doe_levels is None else check_levels(oc.doe_levels, "optics.doe_levels")
        if self.fab_levels is not None:
            from raywave.doe.fabrication import mask_bits

            try:
                mask_bits(self.fab_levels)
            except ValueError as e:
                raise ValueError(f"optics.doe_levels: {e}") from None
        if int(oc.fabricate_from) < 0:
            raise ValueError(f"optics.fabricate_from must be >= 0 (a stage-1 step), got {oc.fabricate_from}")
        self.fab_on = oc.doe_levels is not None or oc.doe_wavelength is not None or oc.doe_material is not None
        if not self.fab_on:
            return
        from raywave.doe import DEFAULT_DESIGN_WAVELENGTH, DEFAULT_MATERIAL

        self.fab_wavelength = float(DEFAULT_DESIGN_WAVELENGTH if oc.doe_wavelength is None else oc.doe_wavelength)
        self.fab_material = DEFAULT_MATERIAL if oc.doe_material is None else oc.doe_material
        doe = self.hl.doe
        if self.fab_levels is not None and doe.quant_levels == self.fab_levels and doe.material_name is not None:
            self._fabricated = True  # a hybrid handed over already fabricated (train_plain_network)
            return
        doe.fabricate(levels=None, wavelength=self.fab_wavelength, material=self.fab_material, wrap=False)
        self._fabricated = False

    def fabricated_at(self, stage: str, step: int) -> bool:
        """Whether the DOE is the quantised element at ``stage``'s ``step``: from stage-1 step
        ``optics.fabricate_from`` on (and in stage 2, the evaluation and the export)."""
        if self.fab_levels is None:
            return False
        if stage in ("stage2", "done"):
            return True
        return stage == "stage1" and step >= int(self.cfg.optics.fabricate_from)

    def _fabrication(self, stage: str, step: int) -> None:
        """Put the DOE in the state of ``stage``/``step`` (idempotent; a resumed run gets it back)."""
        if not self.fab_on:
            return
        want = self.fabricated_at(stage, step)
        if want != self._fabricated:
            self.hl.doe.fabricate(levels=self.fab_levels if want else None, wavelength=self.fab_wavelength,
                                  material=self.fab_material, wrap=want)
            self._fabricated = want
            self._frozen_maps.clear()
            self.stage2_map = None
            self._truth_map = None
