"""The public façade (issue 17): `import raywave` exports the core lazily, `load_lens` / `load_hybrid` take bundled
names, the compatibility aliases of the refactor still resolve to the one implementation."""

import importlib.metadata

import pytest

import raywave


def test_every_exported_name_resolves_and_version_is_the_package_metadata():
    for name in raywave.__all__:
        assert getattr(raywave, name) is not None, name
    assert raywave.__version__ == importlib.metadata.version("raywave")
    assert set(raywave.__all__) <= set(dir(raywave))
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        raywave.nope  # noqa: B018


def test_the_facade_is_the_defining_modules_objects():
    from raywave.assembly.build import load_hybrid
    from raywave.hybrid.hybrid_lens import HybridLens
    from raywave.lens.lens import Lens
    from raywave.models.interface import make_model
    from raywave.training.trainer import Trainer

    assert raywave.Lens is Lens and raywave.HybridLens is HybridLens and raywave.load_hybrid is load_hybrid
    assert raywave.make_model is make_model and raywave.Trainer is Trainer


def test_the_facade_exports_the_mid_system_doe():
    from raywave.assembly.midsystem import load_midsystem, midsystem_from_spec
    from raywave.hybrid.midsystem import MidSystemLens

    assert raywave.MidSystemLens is MidSystemLens and raywave.load_midsystem is load_midsystem
    assert raywave.midsystem_from_spec is midsystem_from_spec


def test_load_lens_and_load_hybrid_take_bundled_names():
    from raywave.lens.build import bundled_lens_path

    a = raywave.load_lens("cooke_triplet")
    b = raywave.load_lens(bundled_lens_path("cooke_triplet"))
    assert a.name == b.name and len(a.surfaces) == len(b.surfaces)
    hl = raywave.load_hybrid("hybrid_asphere")
    assert isinstance(hl, raywave.HybridLens) and hl.doe.shape == (3000, 3000)
    with pytest.raises(FileNotFoundError, match="nor a bundled lens"):
        raywave.load_lens("no_such_lens")
    with pytest.raises(FileNotFoundError, match="nor a bundled lens"):
        raywave.load_hybrid("no_such_lens")


def test_compatibility_aliases_resolve_to_the_one_implementation():
    import raywave.hybrid
    import raywave.hybrid.build
    from raywave.doe import base, fabrication, params

    assert raywave.hybrid.load_hybrid is raywave.load_hybrid
    assert raywave.hybrid.hybrid_from_spec is raywave.hybrid_from_spec
    assert raywave.hybrid.build.load_hybrid is raywave.load_hybrid
    assert params.SumDOE is base.SumDOE is raywave.SumDOE
    from raywave.models import interface
    from raywave.models import base as mbase

    assert interface.PSFModel is mbase.PSFModel and interface.propagate_fields is mbase.propagate_fields
    import torch

    ph = torch.linspace(-7.0, 7.0, 101, dtype=torch.float64)
    lv = base.phase_levels(ph, 8)
    assert (fabrication.quantise_phase(ph.numpy(), 8) == lv.numpy()).all()
    assert torch.equal(base.quantize_phase(ph, 8), lv.to(torch.float64) * (2 * torch.pi / 8))


def test_model_registry_names_its_classes():
    from raywave.models.interface import MODEL_NAMES, MODELS

    assert MODEL_NAMES == ("raywave", "raywave_doe", "paraxial", "pupil", "raytrace", "exit_pupil")
    assert all(cls.name == name for name, cls in MODELS.items())
    with pytest.raises(TypeError):
        MODELS["x"] = object  # read-only
    with pytest.raises(ValueError, match="unknown model 'nope'"):
        raywave.make_model("nope", None)
