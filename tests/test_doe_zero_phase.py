"""A blank DOE's ``exp(iφ)`` is 1: the engine skips its phase map and product (``has_zero_phase``) and the field
after it is the field before it, while every DOE that may carry a phase is still applied."""

import torch

from raywave.doe import BlankDOE, PixelDOE
from raywave.doe.base import has_zero_phase
from raywave.wave import Field


class _Tilted(BlankDOE):
    """A blank DOE's subclass with a phase of its own: not assumed blank."""

    def design_phase_pixels(self, rows, cols):
        return torch.ones(self._count(rows, cols), dtype=torch.float64, device=self.device)


def _field(doe):
    g = doe.sim_grid().window(2, 6, 3, 8)
    env = torch.randn((*g.shape, 2), dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    return Field(torch.view_as_complex(env), g, 0.55, 1.0, (0.0, 0.0))


def test_only_a_plain_blank_doe_has_zero_phase():
    assert has_zero_phase(BlankDOE((8, 8), 0.01))
    assert has_zero_phase(BlankDOE((8, 8), 0.01, design_wavelength=0.5, dispersion="air"))
    assert not has_zero_phase(PixelDOE(torch.zeros(8, 8), 0.01))  # trainable: its phase may move
    assert not has_zero_phase(_Tilted((8, 8), 0.01))


def test_modulate_keeps_a_blank_does_field_and_applies_any_other_phase():
    blank = BlankDOE((8, 8), 0.01)
    f = _field(blank)
    assert blank.modulate(f) is f
    tilted = _Tilted((8, 8), 0.01)
    out = tilted.modulate(_field(tilted))
    assert torch.allclose(out.envelope, f.envelope * torch.exp(torch.tensor(1j, dtype=torch.complex128)))
