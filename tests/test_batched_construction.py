"""Issue 43: a call's field constructions share its traces and are built in memory-bounded groups.

* :meth:`HybridLens.psf_result` traces what its sources share once (chief rays, footprints, the stop rim's images,
  the DOE-aperture diagnostics) and builds and propagates the fields in groups (:data:`FIELD_GROUP_BYTES`): the PSFs
  do not depend on how the sources are grouped (every ray is traced on its own), and the warnings come once per
  call;
* :func:`raywave.imaging.psf_map` without autograd hands a HybridLens up to ``map_sources_per_call`` sources a call;
* the Newton rounds trace every live ray of every construction as one bundle of single-ray rows
  (:func:`raywave.hybrid.coherent.tracing._trace_rows`): the same landing points as one trace per construction.
"""

import warnings

import pytest
import torch

from raywave.assembly.build import load_hybrid
from raywave.hybrid import hybrid_lens as hybrid_mod
from raywave.hybrid.coherent import tracing as tracing_mod
from raywave.imaging import psfmap as psfmap_mod
from raywave.lens.build import bundled_lens_path
from raywave.lens.sources import entrance_plane_z

FIELDS = [(0.0, 0.0), (0.0, 6.0), (4.0, 0.0), (0.0, -6.0), (-4.0, 0.0)]


@pytest.fixture(scope="module")
def asphere():
    return load_hybrid(bundled_lens_path("hybrid_asphere"))


def _psfs(hl, fields, wls, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with torch.no_grad():
            return hl.psf_result(fields, wls, ks=32, rays=24, **kw)


def test_groups_do_not_change_the_psfs(asphere, monkeypatch):
    """One group per built source (a tiny group budget) gives the PSFs, centres and diagnostics of one group for
    the whole call, and of the fields built with :meth:`doe_fields` and propagated (the cache path)."""
    wls = [0.55, 0.47]
    one = _psfs(asphere, FIELDS, wls)
    geo = asphere._accurate_geometry(torch.tensor(FIELDS, dtype=torch.float64), wls, None)
    assert len(asphere._field_groups(geo)) == 1
    monkeypatch.setattr(hybrid_mod, "FIELD_GROUP_BYTES", 1)
    groups = asphere._field_groups(geo)
    assert len(groups) == len(geo.todo) > 1  # every built source with its mirror images
    assert sorted(i for g in groups for i in g) == list(range(len(FIELDS)))
    many = _psfs(asphere, FIELDS, wls)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with torch.no_grad():
            cached = asphere.psf_result(cache=asphere.doe_fields(FIELDS, wls, rays=24), ks=32)
    for other in (many, cached):
        rel = (other.psf - one.psf).abs().sum((-2, -1)) / one.psf.abs().sum((-2, -1))
        assert float(rel.max()) < 1e-12
        assert torch.equal(other.center, one.center)
        assert torch.allclose(other.doe_clipped, one.doe_clipped, rtol=0, atol=1e-15)
        assert torch.equal(other.rays, one.rays)


def test_newton_rows_equal_one_trace_per_construction(asphere):
    """The rows of :func:`_trace_rows` (each ray with its own source and wavelength) land where the rays of one
    :func:`_trace_uv` per source land."""
    lens = asphere.optics
    z = asphere.doe_z()
    ep_z = entrance_plane_z(lens)
    gen = torch.Generator().manual_seed(1)
    fields = torch.tensor([[0.0, 0.0], [0.0, 7.0], [3.0, -5.0]], dtype=torch.float64)
    wls = torch.tensor([0.47, 0.55, 0.66], dtype=torch.float64)
    uv = 0.3 * (torch.rand(3, 40, 2, generator=gen, dtype=torch.float64) - 0.5)
    aim = tracing_mod._Aim(lens, fields[0], wls[:1], None, z, lens.field_type, 1e-6, ep_z)
    x, valid = tracing_mod._trace_rows(aim, uv.reshape(-1, 2), fields.repeat_interleave(40, 0),
                                       wls.repeat_interleave(40))
    for g in range(3):
        with torch.no_grad():
            _, _, at, _ = tracing_mod._trace_uv(lens, uv[g], fields[g], wls[g:g + 1], None, z, lens.field_type,
                                                ep_z=ep_z)
        ref = at.o[0, 0, :, :2]
        assert float((x[40 * g:40 * (g + 1)] - ref).abs().max()) <= 1e-12
        assert torch.equal(valid[40 * g:40 * (g + 1)], at.valid[0, 0])


def test_map_without_grad_takes_the_lens_call_size(asphere):
    """A 10×10×3 map without autograd is one call (≤ ``map_sources_per_call`` sources); with autograd or a field
    cache it keeps the fixed chunk of :func:`default_batch`."""
    per = psfmap_mod.map_call_size(asphere, False, None)
    assert per == asphere.map_sources_per_call >= 300
    assert psfmap_mod._map_chunks(100, 3, None, per) == [(0, 100)]
    assert psfmap_mod.map_call_size(asphere, True, None) is None
    assert psfmap_mod.map_call_size(asphere, False, object()) is None
    assert len(psfmap_mod._map_chunks(100, 3, None, None)) == 13


def test_map_with_grad_on_an_accelerator_takes_the_lens_call_size():
    """With autograd on an accelerator a map's call takes ``map_sources_per_call`` sources too (a meta-device model
    stands in for a GPU's); on the CPU it keeps :func:`default_batch`."""
    import torch

    class Model(torch.nn.Module):
        map_sources_per_call = 512

        def __init__(self, device):
            super().__init__()
            self.w = torch.nn.Parameter(torch.zeros(1, device=device))

    assert psfmap_mod.map_call_size(Model("meta"), True, None) == 512
    assert psfmap_mod.map_call_size(Model("cpu"), True, None) is None
    assert psfmap_mod.map_call_size(Model("meta"), True, object()) is None


def test_construction_functions_take_at_most_ten_parameters():
    """The accurate construction's functions take value types (:class:`~raywave.hybrid.coherent.settings.Source`,
    :class:`~raywave.hybrid.coherent.settings.FieldSettings`, :class:`~raywave.hybrid.coherent.settings.Known`, the tracing's
    ``_Aim``) instead of long parameter lists: at most 10 parameters each (``self`` not counted)."""
    import ast
    import pathlib

    root = pathlib.Path(__file__).resolve().parents[1] / "raywave" / "hybrid"
    files = [root / "coherent" / n for n in ("accurate.py", "tracing.py", "geometry.py", "record.py")]
    files += [root / "hybrid_lens.py", root / "batched.py", root / "mirror.py"]
    long = []
    for path in files:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef):
                a = node.args
                k = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) + bool(a.vararg) + bool(a.kwarg)
                k -= bool(a.args and a.args[0].arg in ("self", "cls"))
                if k > 10:
                    long.append(f"{path.name}:{node.name} ({k})")
    assert not long, long


def test_the_ray_stage_of_all_groups_runs_in_one_pass(asphere, monkeypatch):
    """With many field groups (a tiny group budget) the constructions' ray stages (aiming, Newton inversion, node
    traces) of all groups run together, paused before their fine fields (:data:`raywave.hybrid.coherent.tracing.
    PAUSE`): the Newton inversions are one batched solve per round for the call, not one per group. The PSFs equal
    one ray stage per group (a tiny :data:`RAY_STAGE_NODES`) and the serial construction's pause-free path."""
    wls = [0.55, 0.47]
    monkeypatch.setattr(hybrid_mod, "FIELD_GROUP_BYTES", 1)
    calls = []
    real = tracing_mod._invert_group

    def spy(reqs):
        calls.append(len(reqs))
        return real(reqs)

    monkeypatch.setattr(tracing_mod, "_invert_group", spy)
    together = _psfs(asphere, FIELDS, wls)
    geo = asphere._accurate_geometry(torch.tensor(FIELDS, dtype=torch.float64), wls, None)
    n_built = len(geo.todo) * len(wls)
    assert len(asphere._field_groups(geo)) == len(geo.todo) > 1
    assert calls == [n_built, n_built]  # the coarse and the fine inversion, each of every construction at once
    calls.clear()
    monkeypatch.setattr(hybrid_mod, "RAY_STAGE_NODES", 1)
    per_group = _psfs(asphere, FIELDS, wls)
    assert len(calls) == 2 * len(geo.todo)
    rel = (per_group.psf - together.psf).abs().sum((-2, -1)) / together.psf.abs().sum((-2, -1))
    assert float(rel.max()) < 1e-12
    assert torch.equal(per_group.center, together.center) and torch.equal(per_group.rays, together.rays)


def test_paused_constructions_finish_as_the_unpaused_ones(asphere):
    """run_batched(pause=True) stops every construction after its ray stage (a Paused); run_batched on those
    finishes them: the same fields as one run (and as run_serial)."""
    hl = asphere
    wls = [0.55]
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        geo = hl._accurate_geometry(torch.tensor(FIELDS[:2], dtype=torch.float64), wls, None)
        rows = list(range(len(geo.todo)))
        paused = tracing_mod.run_batched(hl._accurate_constructions(geo, rows, 24, True), pause=True)
        assert all(isinstance(p, tracing_mod.Paused) for p in paused)
        done = tracing_mod.run_batched(paused)
        straight = tracing_mod.run_batched(hl._accurate_constructions(geo, rows, 24, True))
        serial = [tracing_mod.run_serial(g) for g in hl._accurate_constructions(geo, rows, 24, True)]
    for a, b, c in zip(done, straight, serial):
        assert a.box == b.box == c.box
        assert float((a.envelope - b.envelope).abs().max()) == 0.0
        assert float((a.envelope - c.envelope).abs().max()) < 1e-12 * float(c.envelope.abs().max())


def test_an_accelerator_takes_larger_field_groups(asphere, monkeypatch):
    """On an accelerator the fields are grouped up to FIELD_GROUP_BYTES_ACCELERATOR (fewer groups: each is a fixed
    number of kernel launches), on a CPU up to FIELD_GROUP_BYTES."""
    import raywave.utils.devices as devices

    geo = asphere._accurate_geometry(torch.tensor(FIELDS, dtype=torch.float64), [0.55, 0.47], None)
    monkeypatch.setattr(hybrid_mod, "FIELD_GROUP_BYTES", 1)
    assert len(asphere._field_groups(geo)) == len(geo.todo) > 1
    monkeypatch.setattr(devices, "accelerator", lambda x: True)
    assert len(asphere._field_groups(geo)) == 1
    monkeypatch.setattr(hybrid_mod, "FIELD_GROUP_BYTES_ACCELERATOR", 1)
    assert len(asphere._field_groups(geo)) == len(geo.todo)
