"""Where the dispatched aten ops of one PSF-map call go (issue 43): each op attributed to the innermost raywave
function on the Python stack (and, coarser, to a phase of the data path).

The calls are :func:`benchmarks.imaging.ops_case`'s: the first model call of the bundled ``hybrid_asphere``'s N×M×W
map (field points in :func:`raywave.imaging.psf_map`'s order, mirror images together), ks = 64, default edge, no
autograd (and, with ``--grad``, forward + backward of a weighted sum of the PSFs). Prints one JSON object (and
writes it with ``-o``): ops per PSF in total, per phase and for the ``--top`` heaviest functions; and the host
synchronisations per PSF (``syncs_per_psf``, with their ``--top`` sites): the ops whose result the host must read
before it can go on (``_local_scalar_dense``: ``.item()``, ``float()``, ``bool()`` of a tensor; ``nonzero``,
``masked_select``, ``unique``: outputs sized by the data). On a GPU each one stalls the host until the device is
idle (issue 43: "no per-PSF ``.item()`` round trips"). Counted on the CPU, they are a lower bound: a ``.tolist()`` or
``.cpu()`` of a CUDA tensor is a copy to the host, which a CPU run cannot see.

    OMP_NUM_THREADS=1 PYTHONPATH=$PWD python benchmarks/ops_breakdown.py [--map 10x10x3] [--grad] [-o out.json]

The phase of an op is the first of these functions found walking the stack outward from the op (so a trace inside
the Newton inversion counts as ``invert``, a trace for the final node rays as ``node_trace``):
"""

from __future__ import annotations

import argparse
import collections
import os
import sys
import warnings

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)

KS = 64
WAVELENGTHS = (0.66, 0.53, 0.47)

#: (phase, function names that open it): the first match walking outward from an op names its phase
PHASES = (
    ("backward", ("backward",)),
    ("chief_rays", ("chief_rays", "_chief_rays", "chief_ray")),
    ("footprints", ("footprints", "_footprint", "doe_clippings", "stop_rim_images_all", "stop_rim_images_many",
                    "stop_rim_images", "edge_focus_many")),
    ("coarse_start", ("_coarse_start",)),
    ("invert", ("_invert_group", "_invert_to_nodes", "_landing_rounds", "_trace_rows")),
    ("landing_jacobian", ("_landing_and_jacobian",)),
    ("node_trace", ("_trace_nodes", "run_batched")),
    ("node_layout", ("_node_layout",)),
    ("node_maps", ("_node_maps", "_node_stage", "_node_stages", "_node_stage_batch")),
    ("stop_edge_maps", ("_stop_edge_maps", "_stop_edge_batch")),
    ("check_nodes", ("_check_nodes", "_check_nodes_batch")),
    ("fine_field", ("_fine_field", "_window_field", "_fine_fields", "_fine_field_batch")),
    ("field_setup", ("accurate_field_steps", "_common_setup")),
    ("propagation", ("propagate_group", "propagate_fields", "propagate", "modulated_batch", "sensor_psfs")),
)
__doc__ += "".join(f"\n* ``{p}``: {', '.join(fs)}" for p, fs in PHASES) + "\n"

_ROOT = None  # the imported raywave package's folder (set in main: the tree on PYTHONPATH)


def _attribute(frame, phase_of: dict) -> tuple[str, str, str]:
    """``(innermost raywave function 'module:func', phase, the phase's opening function and its raywave caller)``
    of the op dispatched under ``frame``."""
    inner, phase, opener = None, None, None
    f = frame
    while f is not None:
        code = f.f_code
        fn = code.co_filename
        if fn.startswith(_ROOT):
            if inner is None:
                inner = f"{os.path.relpath(fn, _ROOT)[:-3].replace(os.sep, '.')}:{code.co_name}"
            if phase is not None:
                opener += f" < {code.co_name}"
                break
            if code.co_name in phase_of:
                phase, opener = phase_of[code.co_name], code.co_name
        elif phase is None and code.co_name == "backward" and "torch" in fn:
            phase, opener = "backward", "backward"
            break
        f = f.f_back
    return inner or "(outside raywave)", phase or "other", opener or "(none)"


#: aten ops that make the host wait for the device: a scalar read, or an output whose size the data decide
SYNC_OPS = ("_local_scalar_dense", "nonzero", "masked_select", "unique", "_unique2", "unique_consecutive")


def breakdown(fn) -> tuple[int, collections.Counter, collections.Counter, collections.Counter, collections.Counter]:
    """Run ``fn`` counting its aten ops: ``(total, per function, per phase, per phase opener < its caller, host
    synchronisations per raywave function (:data:`SYNC_OPS`))``."""
    from torch.utils._python_dispatch import TorchDispatchMode

    phase_of = {name: p for p, names in PHASES for name in names}
    funcs, phases, openers, syncs = (collections.Counter() for _ in range(4))

    class _Attr(TorchDispatchMode):
        n = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            self.n += 1
            inner, phase, opener = _attribute(sys._getframe(1), phase_of)
            funcs[inner] += 1
            phases[phase] += 1
            openers[opener] += 1
            if func._schema.name.split("::")[-1] in SYNC_OPS:
                syncs[inner] += 1
            return func(*args, **(kwargs or {}))

    with _Attr() as c:
        fn()
    return c.n, funcs, phases, openers, syncs


def _accelerator_sizes() -> None:
    """Take an accelerator's plan on the CPU (the lens traces' chunks, the edge envelope's blocks, the band
    convolution's column chunks and whole batches, the dense interpolation, the one batched evaluation of the
    transfer functions, the shared FFT sizes, the batched field stage: the same values, fewer and larger ops), so
    that the count is the ops a CUDA run dispatches: one switch, :func:`raywave.utils.devices.accelerator`, in trees
    that have it (``RAYWAVE_OPS_FIELD_SAMPLES`` / ``RAYWAVE_OPS_BATCH_BYTES``: smaller batches than an accelerator's,
    for a CPU's memory)."""
    import raywave.hybrid.coherent.accurate as accurate_mod

    if hasattr(accurate_mod, "FIELD_BATCH_SAMPLES_ACCELERATOR"):  # the field stages' padded batches
        cap = os.environ.get("RAYWAVE_OPS_FIELD_SAMPLES")
        accurate_mod.FIELD_BATCH_SAMPLES_ACCELERATOR = int(float(cap)) if cap else \
            accurate_mod.FIELD_BATCH_SAMPLES_ACCELERATOR
    import raywave.hybrid.batched as batched_mod

    try:
        import raywave.utils.devices as devices_mod
    except ImportError:  # trees before the one switch: each module's sizes and checks
        devices_mod = None
    if devices_mod is not None:
        devices_mod.accelerator = lambda x: True
    else:
        import raywave.hybrid.coherent.stop_edge as edge_mod
        import raywave.lens.lens as lens_mod
        import raywave.wave.propagation.band as window_mod
        import raywave.wave.propagation.batch as batch_mod

        pairs = ((lens_mod, "TRACE_CHUNK"), (edge_mod, "ENVELOPE_BLOCK_SAMPLES"), (window_mod, "BAND_CHUNK_BYTES"))
        for mod, name in pairs:
            if not hasattr(mod, name + "_ACCELERATOR"):
                raise SystemExit(f"--accelerator: this tree has no {mod.__name__}.{name}_ACCELERATOR (per-device "
                                 "sizes)")
            setattr(mod, name, getattr(mod, name + "_ACCELERATOR"))
        if hasattr(batch_mod, "_by_source"):  # an accelerator evaluates a batch's transfer functions at once
            batch_mod._by_source = lambda device, b: False
        if hasattr(batched_mod, "_accelerator"):  # and shares FFT sizes between resolved sources
            batched_mod._accelerator = lambda planned: bool(planned)
    cap = os.environ.get("RAYWAVE_OPS_BATCH_BYTES")  # a smaller cap than the accelerator's, for a CPU's memory
    if cap:
        batched_mod.BATCH_BYTES_ACCELERATOR = int(float(cap))


def _count_field_batches() -> list:
    """A list that receives the size of every batch of the batched field stage (issue 43; the accurate construction's
    ``_fine_field_batch``, where this tree has one) while the cases run."""
    import raywave.hybrid.coherent.accurate as accurate_mod

    sizes: list = []
    real = getattr(accurate_mod, "_fine_field_batch", None)
    if real is not None:
        def counted(reqs, *a):
            sizes.append(len(reqs))
            return real(reqs, *a)

        accurate_mod._fine_field_batch = counted
    return sizes


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", default="10x10x3", metavar="NxMxW")
    ap.add_argument("--grad", action="store_true", help="also count forward + backward")
    ap.add_argument("--top", type=int, default=25, help="functions listed")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--accelerator", action="store_true",
                    help="count the ops of the path an accelerator takes (the lens traces, the edge envelope and the "
                         "band convolution in CUDA's block sizes: the same values, fewer blocks)")
    ap.add_argument("--per-construction-fields", action="store_true",
                    help="with --accelerator: the field stage one construction at a time (the accelerator's path "
                         "before the batched field stage, raywave.hybrid.coherent.accurate.BATCHED_FIELD_STAGE)")
    ap.add_argument("--common-fft", action="store_true",
                    help="one FFT size per group of sources (raywave.hybrid.batched.COMMON_FFT, issue 43)")
    ap.add_argument("-o", "--output", default=None)
    args = ap.parse_args()

    import torch

    import raywave
    from imaging import _lens  # noqa: E402  (benchmarks/ is on sys.path)
    from raywave.imaging.psfmap import _map_chunks, _pair_order, field_grid
    try:
        from raywave.imaging.psfmap import map_call_size
    except ImportError:  # a tree from before issue 43's per-call geometry (e.g. main 35b5cba): the fixed chunk
        def map_call_size(*_):
            return None

    global _ROOT
    _ROOT = os.path.dirname(os.path.abspath(raywave.__file__))
    if args.accelerator:
        _accelerator_sizes()
    if args.per_construction_fields:
        import raywave.hybrid.coherent.accurate as accurate_mod

        accurate_mod.BATCHED_FIELD_STAGE = False
    if args.common_fft:
        import raywave.hybrid.batched as batched_mod

        batched_mod.COMMON_FFT = True
    torch.set_num_threads(args.threads)
    warnings.simplefilter("ignore")
    n, m, w = (int(v) for v in args.map.split("x"))
    wls = list(WAVELENGTHS[:w])
    hl = _lens()
    with torch.no_grad():
        hl.psf_result((0.0, 0.0), wls[:1], ks=KS)  # warm-up (first-call costs)
    order = _pair_order(n, m)
    flat = field_grid(hl, (n, m)).reshape(-1, 2)[order]
    per_call = map_call_size(hl, False, None)
    s, e = _map_chunks(n * m, w, None, *([per_call] if per_call else []))[0]  # the no-grad map's first call
    f0 = flat[s:e]
    s, e = _map_chunks(n * m, w, None)[0]  # psf_map(grad=True)'s first call
    f = flat[s:e]

    def nograd():
        with torch.no_grad():
            hl.psf_result(f0, wls, ks=KS)

    def fwd_bwd():
        r = hl.psf_result(f, wls, ks=KS)
        wt = torch.rand(r.psf.shape, dtype=r.psf.dtype, generator=torch.Generator().manual_seed(0))
        (r.psf * wt.to(r.psf.device)).sum().backward()

    out = {"benchmark": "ops_breakdown", "lens": "hybrid_asphere", "grid": [n, m], "wavelengths": wls, "ks": KS,
           "stop_edge": hl.stop_edge, "torch": torch.__version__,
           "path": "accelerator (CUDA block sizes)" if args.accelerator else "cpu", "common_fft": args.common_fft,
           "batched_field_stage": args.accelerator and not args.per_construction_fields}
    cases = [("no_grad", nograd, f0.shape[0] * w)] + ([("grad", fwd_bwd, f.shape[0] * w)] if args.grad else [])
    batches = _count_field_batches()
    for name, fn, k in cases:
        batches.clear()
        total, funcs, phases, openers, syncs = breakdown(fn)
        out[name] = {"psfs_in_call": k, "ops_per_psf": round(total / k, 1),
                     "syncs_per_psf": round(sum(syncs.values()) / k, 2),
                     "sync_sites_per_psf": {f_: round(c / k, 2) for f_, c in syncs.most_common(args.top)},
                     "phases_per_psf": {p: round(c / k, 1) for p, c in phases.most_common()},
                     "openers_per_psf": {o: round(c / k, 1) for o, c in openers.most_common(args.top)},
                     "functions_per_psf": {f_: round(c / k, 1) for f_, c in funcs.most_common(args.top)},
                     "field_stage_batches": list(batches)}
    emit_json(out, args.output)


if __name__ == "__main__":
    main()
