"""Ray bundles: batched rays with position, direction, wavelength, validity and optical path length.

Every tensor has the bundle's leading batch shape ``S`` (any shape, e.g. ``(n_fields, n_wl, n_rays)``):

========== =========== ===========================================================
field      shape       meaning
========== =========== ===========================================================
o          S + (3,)    position (mm), global coordinates
d          S + (3,)    unit direction cosines (travel toward +z in a sequential lens)
wavelength S (bcast)   vacuum wavelength (µm); may be any shape broadcastable to S
valid      S           bool: False once the ray missed a surface, left an aperture or met TIR
opl        S           optical path length travelled so far (mm), in float64 for coherent work
========== =========== ===========================================================

Bundles are immutable value objects: tracing returns new bundles. The dtype is chosen explicitly
(float64 by default) and never taken from torch's global default.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

DEFAULT_DTYPE = torch.float64


@dataclass(frozen=True)
class RayBundle:
    """A batch of rays (see the module docstring for shapes and units)."""

    o: torch.Tensor
    d: torch.Tensor
    wavelength: torch.Tensor
    valid: torch.Tensor
    opl: torch.Tensor

    @staticmethod
    def create(o, d, wavelength, valid=None, opl=None, dtype: torch.dtype = DEFAULT_DTYPE, device=None) -> "RayBundle":
        """Build a bundle; ``d`` is normalised. ``o``/``d``: S+(3,) mm / direction; ``wavelength`` µm."""
        o = torch.as_tensor(o, dtype=dtype, device=device)
        d = torch.as_tensor(d, dtype=dtype, device=o.device)
        o, d = torch.broadcast_tensors(o, d)
        d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
        shape = o.shape[:-1]
        wavelength = torch.as_tensor(wavelength, dtype=dtype, device=o.device)
        if valid is None:
            valid = torch.ones(shape, dtype=torch.bool, device=o.device)
        else:
            valid = torch.as_tensor(valid, dtype=torch.bool, device=o.device).expand(shape)
        if opl is None:
            opl = torch.zeros(shape, dtype=dtype, device=o.device)
        else:
            opl = torch.as_tensor(opl, dtype=dtype, device=o.device).expand(shape)
        return RayBundle(o=o, d=d, wavelength=wavelength, valid=valid, opl=opl)

    @property
    def shape(self) -> torch.Size:
        return self.o.shape[:-1]

    @property
    def dtype(self) -> torch.dtype:
        return self.o.dtype

    @property
    def device(self) -> torch.device:
        return self.o.device

    @property
    def x(self) -> torch.Tensor:
        return self.o[..., 0]

    @property
    def y(self) -> torch.Tensor:
        return self.o[..., 1]

    @property
    def z(self) -> torch.Tensor:
        return self.o[..., 2]

    def replace(self, **changes) -> "RayBundle":
        return replace(self, **changes)

    def __getitem__(self, index) -> "RayBundle":
        """Index the batch dimensions (not the xyz axis)."""
        wl = torch.broadcast_to(self.wavelength, self.shape)
        idx = index if isinstance(index, tuple) else (index,)
        vec = idx + (slice(None),) if Ellipsis in idx else idx  # keep the xyz axis last
        return RayBundle(self.o[vec], self.d[vec], wl[index], self.valid[index], self.opl[index])

    def unbind(self, dim: int = 0) -> tuple["RayBundle", ...]:
        """The bundles along batch dimension ``dim`` (≥ 0), as :meth:`__getitem__` of each index gives them, from one
        ``unbind`` per field (a view each; indexing element by element dispatches several ops per element)."""
        wl = torch.broadcast_to(self.wavelength, self.shape)
        parts = (self.o.unbind(dim), self.d.unbind(dim), wl.unbind(dim), self.valid.unbind(dim), self.opl.unbind(dim))
        return tuple(RayBundle(*f) for f in zip(*parts))

    def propagate_to_z(self, z: float | torch.Tensor, n: float | torch.Tensor = 1.0) -> "RayBundle":
        """Straight propagation to the plane ``z`` (mm) in a medium of index ``n``; OPL accumulates n·t."""
        t = (z - self.o[..., 2]) / self.d[..., 2]
        o = self.o + t.unsqueeze(-1) * self.d
        return self.replace(o=o, opl=self.opl + n * t)

    def to(self, device=None, dtype=None) -> "RayBundle":
        def cast(t):
            return t.to(device=device, dtype=dtype) if t.is_floating_point() else t.to(device=device)

        return RayBundle(cast(self.o), cast(self.d), cast(self.wavelength), self.valid.to(device), cast(self.opl))
