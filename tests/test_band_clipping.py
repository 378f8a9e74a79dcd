"""A DOE aperture that cuts the stop edge's diffraction ripples beyond the geometric beam is named
(:class:`~raywave.hybrid.DOEApertureWarning` of kind "band"), not silent: the estimate of the blocked power
(``FieldInfo.band_clipped``, from the node maps' knife-edge intensity) against what the cut does to the PSF (the same
lens with a DOE large enough to hold the band)."""
import warnings

import pytest
import torch

from raywave.assembly import load_hybrid
from raywave.hybrid import DOEApertureWarning
from raywave.lens.build import resolve_lens_path

WL = [0.53]


def _hybrid(size: float):
    # the Fresnel step (the default's step for a DOE with a phase): a blank DOE on axis would take the exact cut
    return load_hybrid(resolve_lens_path("hybrid_asphere"), doe_size=(size, size), edge_step="fresnel")


def _psf_and_warnings(hl):
    with warnings.catch_warnings(record=True) as caught, torch.no_grad():
        warnings.simplefilter("always")
        res = hl.psf_result([(0.0, 0.0)], WL, ks=32)
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore", DOEApertureWarning)  # (the same call's warning again)
        info = hl.doe_fields([(0.0, 0.0)], WL)[0][0].info
    return res.psf, info, [w.message for w in caught if isinstance(w.message, DOEApertureWarning)]


def test_a_doe_that_cuts_the_edge_ripples_warns_and_its_estimate_bounds_the_psf_change():
    """On axis the bundled asphere's beam is 0.73 mm across on the DOE plane; a 0.8 mm DOE holds it whole (no
    geometric clipping) but cuts the edge's ripple band (1.00 mm; 1.07 mm before the short-reach band of 2026-12-01,
    whose 4 zones on axis replaced 5): the warning names the band's share and the DOE
    that holds it, and the PSF moves (against a 2 mm DOE) by 0.3 – 4× the estimate, as measured on the bundled lens
    at 0.76 – 1.05 mm and 11°."""
    ref, ref_info, ref_warned = _psf_and_warnings(_hybrid(2.0))
    assert ref_info.band_clipped == 0.0 and not ref_warned  # the grid holds the band: not even read
    psf, info, warned = _psf_and_warnings(_hybrid(0.8))
    assert info.clipped == 0.0 and 1e-3 < info.band_clipped < 1e-2, info
    assert len(warned) == 1 and warned[0].kind == "band", [str(w) for w in warned]
    text = str(warned[0])
    assert "diffraction ripples beyond the beam's geometric edge" in text and "mm DOE aperture" in text
    need = float(text.split("; a DOE of ")[1].split(" mm square holds the ripple band")[0])
    assert need == pytest.approx(2 * info.band_half, rel=1e-2) and 0.9 < need < 1.2
    moved = float((psf - ref).abs().sum() / ref.abs().sum())
    assert 0.3 * info.band_clipped < moved < 4 * info.band_clipped, (moved, info.band_clipped)


def test_a_doe_that_holds_the_band_but_for_a_trace_stays_quiet():
    """A 0.95 mm DOE leaves ~1e-4 of the ripple band's power outside (below BAND_CLIP_WARN): no warning (9.3e-5
    with the 1.00 mm band of 4 zones; the 1 mm DOE of the 5-zone band's test now holds it all)."""
    _, info, warned = _psf_and_warnings(_hybrid(0.95))
    assert 0.0 < info.band_clipped < 5e-4 and not warned


def test_the_band_warning_survives_a_map_merge_and_pickling():
    """psf_map merges a map's DOEApertureWarnings one per kind; the kind survives pickling (multi-process
    training)."""
    import pickle

    w = DOEApertureWarning("", [(2e-3, 0.5, "field [0.0, 0.0] at 0.53 µm")], (0.8, 0.8), "call", "band")
    back = pickle.loads(pickle.dumps(w))
    assert back.kind == "band" and str(back) == str(w)
    merged = DOEApertureWarning.merged([w, back], "map")
    assert merged.kind == "band" and str(merged).startswith("2 sources (field × wavelength × depth) of this map")


def test_the_caustic_fallbacks_window_loss_is_named_on_a_mid_system_plane():
    """Issue 46's sweep case: a 100 µm grating in the Cooke triplet at 0.45 µm, the engine's plane 40 mm after the
    last vertex and 0.8 mm wide. The ±1 orders' field is built by the caustic fallback (the plane lies near the
    focus) and carried to the plane, whose grid holds their beams but not their ripple bands: 0.42 % of their power
    lost (1.41e-3 in efficiency, silent before). The warning's fraction is the power the 0.8 mm plane holds less than
    a 1.6 mm one (which loses 1e-10)."""
    import raywave
    from raywave.doe.params import GratingDOE
    from raywave.hybrid.midsystem import MidSystemLens

    lens = raywave.load_lens("cooke_triplet")
    doe = GratingDOE(0.1, 1000, 0.012, material="FUSED_SILICA")
    doe.fabricate(2)

    def first_order(size):
        ml = MidSystemLens(lens, doe, 1, 3.0, final_distance=40.0, final_size=size, final_pitch=1e-3,
                           sensor_pitch=2e-3, min_efficiency=0.05).with_edge("exit_pupil", "adaptive")
        with warnings.catch_warnings(record=True) as caught, torch.no_grad():
            warnings.simplefilter("always")
            fd = ml.order_lens(1.0, False).doe_fields([(0.0, 0.0)], [0.45])[0][0]
        power = float(torch.view_as_real(fd.envelope).square().sum())
        return fd.info, power, [w.message for w in caught if isinstance(w.message, DOEApertureWarning)]

    small, p_small, warned = first_order(0.8)
    wide, p_wide, quiet = first_order(1.6)
    assert small.edge_step == "fresnel" and small.clipped == 0.0 and not small.band_total
    assert len(warned) == 1 and warned[0].kind == "band" and not quiet and wide.band_clipped < 1e-8
    assert 3e-3 < small.band_clipped < 6e-3
    assert small.band_clipped == pytest.approx(1.0 - p_small / p_wide, rel=0.05)
