"""A CPU stand-in for a second device (tests/test_device_guard.py): while :class:`StrayTensors` is active, a
tensor factory called from raywave's code without a ``device`` (``torch.zeros(3)``, ``torch.tensor([...])``,
``torch.rand(..., generator=g)``, ...) makes a *meta* tensor instead of a CPU one. On a GPU such a tensor would
land on the CPU beside the lens's CUDA tensors; here it fails at once (a meta tensor has no data), naming the
line, so the device bugs that only a GPU would show are caught on a machine without one.

Exempt: module constructors (``__init__``, ``__post_init__``, ``_param``) and the builders of lenses from files
(raywave/io, lens/build.py, assembly/build.py): a module is built on the CPU and moved with ``.to(device)``.
``torch.as_tensor(t)`` / ``torch.tensor(t)`` of a tensor keep its device, as they do without a default device.
"""

from __future__ import annotations

import sys

import torch
from torch.overrides import TorchFunctionMode

FACTORIES = {torch.tensor, torch.as_tensor, torch.asarray, torch.zeros, torch.ones, torch.empty, torch.full,
             torch.arange, torch.linspace, torch.logspace, torch.eye, torch.rand, torch.randn, torch.randint,
             torch.randperm, torch.scalar_tensor}
_EXEMPT_FUNCTIONS = ("__init__", "__post_init__", "_param")
_EXEMPT_FILES = ("/raywave/io/", "/raywave/lens/build.py", "/raywave/assembly/build.py")


def _library_call(frame) -> bool:
    path = frame.f_code.co_filename.replace("\\", "/")
    return ("/raywave/" in path and frame.f_code.co_name not in _EXEMPT_FUNCTIONS
            and not any(e in path for e in _EXEMPT_FILES))


class StrayTensors(TorchFunctionMode):
    """Factory calls without a device in raywave's data path make meta tensors (see the module docstring)."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in FACTORIES and kwargs.get("device") is None and _library_call(sys._getframe(1)):
            copies_a_tensor = func in (torch.as_tensor, torch.tensor, torch.asarray) and args and torch.is_tensor(
                args[0])
            if not copies_a_tensor:
                kwargs = dict(kwargs, device="meta")
        return func(*args, **kwargs)
