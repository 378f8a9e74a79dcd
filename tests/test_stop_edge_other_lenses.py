"""Issue 47 on lens classes beyond the four of tests/test_stop_edge_references.py: the default PSF (``raywave psf``'s
defaults: exit-pupil stop edge, ``edge_step="adaptive"``, the lens file's default blank DOE) of real lens files from
the OpticExplorer Optics Database (tests/data/opticsdatabase, MIT, attributed there) against the Huygens exit-pupil
PSF with its stop edge at the stop rim's images (``huygens_psf(sphere="rim_images")``, ``n_pupil="auto"``, its levels
agreeing to 1e-6), the reference's own error beside the figure. Slow (the reference's pupil sum).

The sweep behind it (h47c, 2026-11-29; ``benchmarks/stop_edge_references.py "file:PATH:FRAC[:PITCH_UM]" --sphere
rim_images --tol 1e-6``, benchmarks/results/stop_edge_other_lenses_2026-11-29_xv_h47c.json, docs/ray-wave.md
"Other lens classes") covers a Tessar, a telephoto, a Planar, an air-spaced achromat objective and a catalogue
cemented achromat; the cases that hold are pinned here, the others are described there. Session xxiv's seeded
pick (h47v, ``--pick``: a slow wide angle, a telescope objective, a telecentric lens with a finite object, and seven
more, benchmarks/results/stop_edge_new_lenses_2026-11-30_xxiv_h47v.json) adds three that hold with a margin.
"""

import warnings
from pathlib import Path

import pytest
import torch

DATA = Path(__file__).resolve().parent / "data" / "opticsdatabase"
#: the reference's own error estimate must be below this (resolved polar levels agree to ~1e-10)
REF_TOL = 1e-5


def _default_and_reference(path: Path, frac: float, pitch: float | None, doe_distance: float | None = None):
    """``(default psf (32, 32), Huygens result)`` at ``frac`` of the file's largest field (in its own field type: an
    angle, or an object height for a finite object), primary wavelength, ks 32, as the benchmark's ``file:``
    cases; ``doe_distance`` (mm after the last vertex) moves the default blank DOE's plane."""
    from raywave.assembly.build import load_hybrid
    from raywave.lens.build import load_lens
    from raywave.models.exit_pupil import huygens_psf

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lens = load_lens(path)
        fld = (0.0, frac * max(abs(float(f)) for f in lens.fields))
        extra = {} if doe_distance is None else {"doe_distance": doe_distance}
        hl = load_hybrid(path, sensor_pitch=pitch, fields=[list(fld), [0.0, 0.0]], field_type=lens.field_type,
                         **extra)
        wl = hl.lens.primary_wavelength
        with torch.no_grad():
            r = hl.psf_result(fld, wl, ks=32)
            ref = huygens_psf(hl.lens, fld, wl, ks=32, pitch=hl.sensor_pitch,
                              center=tuple(float(c) for c in r.center[0, 0]), n_pupil="auto",
                              sensor_z=float(hl.sensor_z()), max_n_pupil=1024, sphere="rim_images", tol=1e-6)
    return r.psf[0, 0], ref


CASES = {
    # name: (file, field fraction, sensor pitch mm or None: the DOE pitch) -> measured (docstring below)
    "telephoto": ("Cosina Voigtlander Tele-Dynar 100mm f6.3.zmx", 0.7, 3e-3),
    "achromat": ("Telescope Fraunhofer.zmx", 1.0, None),
    "tessar_on_axis": ("Zeiss Tessar f2.8 50mm.zmx", 0.0, None),
    "wide_angle_on_axis": ("Fujifilm Fujinon-SW 65mm F5.6.zmx", 0.0, None),
    "steinheil": ("Telescope Steinheil.zmx", 1.0, None),
    "telecentric_on_axis": ("Telecentric USP4929066.zmx", 0.0, None),
    "telecentric_off_axis": ("Telecentric USP4929066.zmx", 0.7, None),
    "telecentric_tandem_off_axis": ("Telecentric Tandem Jps46-2940.zmx", 0.7, None),
    "tessar_off_axis": ("Zeiss Tessar f2.8 50mm.zmx", 0.7, None),
    "edmund_doublet_on_axis": ("Edmund 32-303.zmx", 0.0, None),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(CASES))
def test_default_psf_of_other_lens_classes_within_1e_3_of_the_converged_reference(name):
    """Measured (h47c): the Cosina Voigtländer Tele-Dynar 100 mm F/6.3 (a telephoto, 11.8° field) at 0.7 field
    (8.25°), 3 µm pixels: 1.66e-4 (the Fresnel step; the reference's own error 3.0e-9; the DOE-plane edge 1.1e-2);
    the Fraunhofer telescope objective (an air-spaced achromat, 100 mm F/7, 0.57° field) at full field, its 2.7 µm
    DOE pitch as the pixels: 3.91e-4 (the Fresnel step; own error 5.4e-10; the DOE-plane edge 6.7e-4); the Zeiss
    Tessar 50 mm F/2.8 on axis: 4.42e-4 (2026-11-30 xxiii; own error 8.2e-11; 4.0e-4 – 5.0e-4 with the DOE 5.7 –
    23 mm before focus; 2.75e-3 in h47c's sweep and at bc9381a, 4.63e-4 at 11a3346 on the same plane: fixed by session
    xxii's changes to the Fresnel step). Since 2026-11-30 (xxiv, h47v: a seeded pick of lens kinds the tests lacked,
    benchmarks/results/stop_edge_new_lenses_2026-11-30_xxiv_h47v.json): the Fujinon-SW 65 mm F/5.6 (a 6×9 wide
    angle, 38° field) on axis: 5.70e-5 (the Fresnel step on the half-way plane; own error 1.9e-10; the DOE-plane
    edge 3.9e-3); the Steinheil telescope objective (100 mm F/7, 0.57°) at full field: 4.04e-4 (own error 5.2e-10;
    the DOE-plane edge 6.8e-4); the telecentric lens of US 4,929,066 (F/4.5, a finite object, image-space
    telecentric, its exit pupil 3.4 m before the DOE plane) on axis: 2.30e-4 (own error 5.6e-9), at 0.7 field 1.75e-4
    (own error 5.8e-7) since it takes the exit-pupil edge (2026-12-01, class D; the DOE-plane edge it fell back to
    before: 4.27e-4 / 3.82e-3). The Telecentric Tandem (JP S46-2940, F/3.5, its exit pupil ~30 m away, the rim images
    on both sides of the DOE plane) at 0.7 field: 7.76e-5 (own error 4.8e-8; on axis 7.68e-5; the DOE-plane edge
    5.1e-3 / 9.8e-3; 1.03e-2 on axis before its far rim images were placed on one side)). The Tessar at 0.7 field (16.4°): 3.56e-4 (2026-11-30 xxiv; own error 1.4e-11; the DOE-plane edge
    6.2e-2). Since h44e (class E: a .zmx stop's own CLAP is its hard edge): the Edmund 32-303 doublet (f 20 mm, ENPD
    F/3.2, its stop's CLAP 0.9 of the ENPD's radius) on axis: 1.37e-4 (own error 1.4e-9; before, with the CLAP
    dropped, 1.51e-3 and no verdict: the reference did not converge, 1.9e-3 at 960 nodes)."""
    fname, frac, pitch = CASES[name]
    psf, ref = _default_and_reference(DATA / fname, frac, pitch)
    err = float((psf - ref.psf).abs().sum())
    print(f"{name} at {frac} field: {err:.3g} from the Huygens PSF (its own error ~{ref.error_estimate:.2g}, "
          f"levels {ref.levels})")
    assert ref.error_estimate is not None and ref.error_estimate < REF_TOL
    assert err < 1e-3


@pytest.mark.slow
@pytest.mark.parametrize("doe_distance, bound", [(None, 6.0e-4), (9.0, 4.0e-4), (11.0, 6.0e-4)])
def test_olympus_wide_angle_off_axis_within_1e_3_at_every_doe_plane(monkeypatch, doe_distance, bound):
    """Issue 47 class C (h47c, 2026-12-01): the Olympus M.Zuiko 12 mm F/2 (45.6° field) at 0.7 field (31.9°, 3 µm
    pixels) with its blank DOE on its default plane (12.87 mm after the last vertex, 2.2 mm before the sensor) /
    9 / 11 mm after the last vertex (6.0 / 4.0 mm before the sensor): 4.88e-4 / 3.42e-4 / 4.86e-4 from the converged
    rim-image Huygens PSF (own error 1.8e-11); before, 1.80e-3 / 3.99e-4 / 7.02e-4. Two causes: the node inversion
    lost the stretched side's rim strip and ripple band (tests/test_invert_backtrack.py), and on the default and
    11 mm planes the rays past the compressed side's rim fold within the band (tests/test_band_fold.py: now the
    caustic fallback's plane, 2.4 / 2.1 mm before). Run with 16 GiB allowed and under a lock of big runs: the
    fallback's window peaks at 8.3 GB RSS (the 9 mm plane, built in place, 2.7 GB); 3.3 min for the three."""
    monkeypatch.setenv("RAYWAVE_MEMORY_LIMIT", "16GiB")
    psf, ref = _default_and_reference(DATA / "Olympus M.Zuiko 12mm F2.0.zmx", 0.7, 3e-3, doe_distance)
    err = float((psf - ref.psf).abs().sum())
    print(f"Olympus 0.7 field, DOE {doe_distance} mm after the last vertex: {err:.3g} (own error "
          f"~{ref.error_estimate:.2g})")
    assert ref.error_estimate is not None and ref.error_estimate < REF_TOL
    assert err < bound


@pytest.mark.slow
@pytest.mark.parametrize("fname, frac", [("Zeiss Planar 2.880.zmx", 0.7), ("Zeiss Planar 2.880.zmx", 1.0),
                                         ("Nikon AF-S Nikkor 300mm f2.8D IF-ED II.zmx", 0.7)])
def test_class_b_fast_lenses_off_axis_within_1e_3(monkeypatch, fname, frac):
    """Issue 47 class B (h47f, 2026-12-01): the DOE plane past a fold of the rays continued past the stop's rim
    (the caustic fallback's estimate, band_fold) and the fallback's plane too wide for the plain carry. The Zeiss
    Planar 80 mm F/2.8 at 0.7 / 1.0 field (3 µm pixels): built on the farthest plane before the fold that fits (14.9 /
    17.5 mm before the DOE plane), **4.84e-4 / 4.85e-4** (own error 2.2e-11 / 7.9e-12; before 1.21e-2 / 2.41e-2 on
    the plane itself, the DOE-plane edge 2.84e-2 / 2.32e-2). The Nikon AF-S 300 mm f/2.8 at 0.7 field: no plane
    before the fold fits (12 400 – 16 162 samples a side), the scaled carry from the fallback's plane (38.3 mm
    before) on a lattice 4.2× the DOE pitch: **3.10e-4** (own error 5.9e-11; before 2.99e-3, the DOE-plane edge
    7.98e-3). 16 GiB allowed, under a lock of big runs: peak RSS 10.2 / 12.7 / 6.3 GB; 18 min for the three on
    a loaded 2-core machine."""
    monkeypatch.setenv("RAYWAVE_MEMORY_LIMIT", "16GiB")
    psf, ref = _default_and_reference(DATA / fname, frac, 3e-3)
    err = float((psf - ref.psf).abs().sum())
    print(f"{fname} at {frac} field: {err:.3g} from the Huygens PSF (own error ~{ref.error_estimate:.2g})")
    assert ref.error_estimate is not None and ref.error_estimate < REF_TOL
    assert err < 1e-3
