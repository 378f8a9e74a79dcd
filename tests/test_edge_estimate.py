"""The adaptive edge step's error estimate (issue 47): ``HybridLens(edge_step="adaptive")``, the default, keeps the
Fresnel step where :func:`raywave.hybrid.coherent.exit_pupil.fresnel_step_estimates` says it holds 1e-3 on the PSF
crop and takes the exact construction (``"asm"``) elsewhere where it fits. Calibration and measurements:
benchmarks/edge_estimate.py (benchmarks/results/edge_estimate_2026-11-30_xxiii_h47a.json), docs/ray-wave.md "Where
each edge step holds"."""

import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
import wave_truth_doe as W  # noqa: E402
from test_far_tails import PS, RINGS, WL, rings  # noqa: E402

import raywave.hybrid.coherent.exit_pupil as XP  # noqa: E402
from raywave.doe import PixelDOE  # noqa: E402
from raywave.doe.base import BlankDOE  # noqa: E402
from raywave.hybrid import HybridLens, StopEdgeWarning  # noqa: E402
from raywave.hybrid.coherent import stop_rim_images  # noqa: E402
from raywave.lens.lens import Lens  # noqa: E402
from raywave.materials import get_material  # noqa: E402
from raywave.surfaces.aperture import CircularAperture  # noqa: E402
from raywave.surfaces.geometry import Plane  # noqa: E402
from raywave.surfaces.interaction import IdealLens  # noqa: E402
from raywave.surfaces.surface import Surface  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore::raywave.hybrid.SensorCropWarning")

N, PITCH = 1000, 1e-3


def lens_a_hybrid(d: float, blank: bool = False, **kw) -> HybridLens:
    """Lens A (ideal, f 10 mm, F/12.5, the stop on it), a 1 mm DOE of 1 µm pixels ``d`` mm after it (``10 − d`` mm
    before the focus): a zero-phase pixel DOE (not blank: the adaptive step does not cut the edge on its plane), or
    with ``blank`` a :class:`BlankDOE`; 2 µm sensor pixels."""
    stop = Surface(Plane(), get_material("AIR"), 10.0, aperture=CircularAperture(0.4), interaction=IdealLens(10.0),
                   is_stop=True)
    doe = BlankDOE(N, PITCH) if blank else PixelDOE(torch.zeros(N, N, dtype=torch.float64), PITCH)
    return HybridLens(Lens([stop], wavelengths=(WL,), primary=0), doe, d, sensor_pitch=PS, **kw)


def _step(hl: HybridLens, ks: int, wl: float = WL) -> str:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StopEdgeWarning)
        return hl.doe_fields([(0.0, 0.0)], wl, crop_reach=hl.crop_reach(ks))[0][0].info.edge_step


def test_the_estimate_takes_the_exact_step_where_the_fresnel_step_breaks():
    """Lens A (measured whole-crop rel L1 of the Fresnel step against the Rayleigh–Sommerfeld integral): 1 mm before
    the focus (N_F 3.2) 1.07e-2 already on a 32-pixel crop → "asm" (1.1e-4); 3 mm before it 2.1e-4 on 32 pixels
    (kept) and 1.64e-3 on 128 (→ "asm", 1.5e-4); a blank DOE on this sphere keeps the cut on the DOE plane."""
    assert _step(lens_a_hybrid(9.0), 32) == "asm"
    assert _step(lens_a_hybrid(9.0), 128) == "asm"
    assert _step(lens_a_hybrid(7.0), 32) == "fresnel"
    assert _step(lens_a_hybrid(7.0), 128) == "asm"
    assert _step(lens_a_hybrid(9.0, blank=True), 128) == "doe"
    assert _step(lens_a_hybrid(9.0, edge_step="fresnel"), 128) == "fresnel"  # an explicit step is kept


def test_the_estimate_keeps_the_fresnel_step_on_the_bundled_asphere():
    """The bundled hybrid_asphere's 64-pixel crops (the map's) reach 2.6 – 3.12 of the edge's zones (at most
    FRESNEL_REACH_ZONES = 3.5), its curvature ratio ≤ 0.13: the Fresnel step at every field and wavelength."""
    from raywave.assembly.build import load_hybrid
    from raywave.lens.build import bundled_lens_path

    hl = load_hybrid(bundled_lens_path("hybrid_asphere"))
    optics = hl.optics
    for wl in (0.47, 0.53, 0.66):
        n = float(optics.surfaces[-1].material.n(torch.tensor([wl], dtype=torch.float64)))
        rims = [stop_rim_images(optics, f, wl, None) for f in ((0.0, 0.0), (0.0, 12.25), (0.0, 17.5), (12.37, 12.37))]
        ests = XP.fresnel_step_estimates(rims, (wl, n), (hl.doe_z(), hl.sensor_z()), hl.crop_reach(64),
                                         hl.doe.pitch / hl.oversample, XP.obscuration_fraction(optics))
        for e in ests:
            assert e is not None and XP.fresnel_step_holds(e), (wl, e)
            assert 2.5 < e[0] < 3.2 and e[2] < 0.15


def test_mixed_steps_in_one_call_match_their_own_calls():
    """4 mm before the focus on a 160-pixel crop the crop's reach in zones goes as 1/√λ (3.76 at 0.55 µm): 0.45 µm
    takes the exact step, 0.75 µm keeps the Fresnel step, in one batched call (each source its own step), each the
    same as its own call."""
    hl = lens_a_hybrid(6.0)
    assert [_step(hl, 160, wl) for wl in (0.45, 0.75)] == ["asm", "fresnel"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StopEdgeWarning)
        with torch.no_grad():
            both = hl.psf_result([(0.0, 0.0)], [0.45, 0.75], ks=160).psf[0]
            alone = [hl.psf_result([(0.0, 0.0)], wl, ks=160).psf[0, 0] for wl in (0.45, 0.75)]
    for j in range(2):
        assert float((both[j] - alone[j]).abs().max()) < 1e-12


def test_where_the_exact_step_does_not_fit_the_fresnel_step_stays_with_a_warning(monkeypatch):
    """A beam over the exact step's limits on the exit-pupil plane (here AUTO_ASM_SAMPLES and FALLBACK_ASM_SAMPLES
    lowered to 8 samples): the Fresnel step with a StopEdgeWarning naming the estimate and the memory limit."""
    monkeypatch.setattr(XP, "AUTO_ASM_SAMPLES", 8)
    monkeypatch.setattr(XP, "FALLBACK_ASM_SAMPLES", 8)
    hl = lens_a_hybrid(7.0)
    with pytest.warns(StopEdgeWarning, match=r"error estimate.*RAYWAVE_MEMORY_LIMIT"):
        fd = hl.doe_fields([(0.0, 0.0)], WL, crop_reach=hl.crop_reach(128))[0][0]
    assert fd.info.edge_step == "fresnel"


@pytest.mark.slow
def test_lens_a_near_focus_default_matches_the_rayleigh_sommerfeld_integral():
    """Lens A, the DOE 1 mm before the focus (N_F 3.2), a 128-pixel crop of 2 µm, the default edge (a zero-phase
    DOE: the exact construction by the estimate) against the converged Rayleigh–Sommerfeld integral. Measured:
    whole crop 1.3e-4 (the Fresnel step, the default before: 4.3e-2); rings 5.7e-5 / 4.3e-4 / 4.6e-4 / 4.9e-4 /
    1.0e-3 at 0–10 / 10–30 / 30–60 / 60–90 / 90–126 µm (Fresnel 1.2e-3 / 2.7e-2 / 0.44 / 0.67 / 0.91)."""
    ref = W.airy_reference(W.TwoLensSystem(), PS, 128)
    hl = lens_a_hybrid(9.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        e = hl.psf_result([(0.0, 0.0)], WL, ks=128).psf[0, 0].detach().numpy()
    whole = float(np.abs(e / e.sum() - ref / ref.sum()).sum())
    ring = rings(e, ref)
    print(f"whole {whole:.2e}, rings {[f'{v:.1e}' for v in ring]} at {RINGS}")
    assert whole < 3e-4
    assert max(ring[:4]) < 1e-3 and ring[4] < 2e-3


# ------------------------------------------------------------------ a sensor far from the focus (class J)
def _doublet_on_sensor(sensor: float, plane: float | None, **kw):
    """tests/test_midsystem_zmx.py's doublet without its DOE (focus ≈ 35 mm after its last vertex at 0.55 µm), its
    sensor ``sensor`` mm after the last vertex, a blank DOE of 2 µm pixels ``plane`` mm after it (None: the file's
    default plane), 2 µm sensor pixels; ``kw`` to ``hybrid_from_spec`` (``stop_edge``, ``edge_step``). Also
    benchmarks/defocused_sensor.py's doublet."""
    from test_midsystem_zmx import DOUBLET

    from raywave.assembly.build import hybrid_from_spec
    from raywave.io.zmx import read_zmx

    with __import__("tempfile").TemporaryDirectory() as d:
        path = Path(d) / "doublet.zmx"
        path.write_text(DOUBLET)
        spec = read_zmx(path)
    del spec["surfaces"][1]["doe"]
    spec["surfaces"][-1]["thickness"] = sensor
    return hybrid_from_spec(spec, doe_pitch=0.002, sensor_pitch=0.002, doe_distance=plane, **kw)


def _doublet_estimate(sensor: float, plane: float):
    hl = _doublet_on_sensor(sensor, plane)
    rim = stop_rim_images(hl.lens, (0.0, 0.0), 0.55, None, bound=(hl.doe_z(), XP.EXIT_PUPIL_FAR))
    return XP.fresnel_step_estimates([rim], (0.55, 1.0), (hl.doe_z(), hl.sensor_z()), hl.crop_reach(32),
                                     hl.doe.pitch)[0]


def test_a_crop_inside_the_rim_rays_ring_counts_the_ring_in_its_reach():
    """Class J (docs/ray-wave.md): with the doublet's sensor 5.5 mm past its focus (~100 waves) every rim ray lands
    ~0.6 mm from the 32-pixel crop (reach 0.047 mm), and the edge waves that reach the crop leave the DOE plane that
    much farther from the rim: on the file's plane (half the gap, 20 mm) the Fresnel step reads 1.44e-3 from the
    converged Huygens reference with the ring's band (1.38e-1 with the in-focus band; benchmarks/defocused_sensor.py),
    and the estimate rejects it (4.6 zones; the crop's reach alone: 0.34); on a plane 5 mm after the lens, 6.7e-5
    from it, the estimate keeps it; in focus (34.5 mm, 1.75e-4) the estimate is the crop's reach alone, as before."""
    far, near = _doublet_estimate(40.0, 20.0), _doublet_estimate(40.0, 5.0)
    assert not XP.fresnel_step_holds(far) and far[0] > 4.0
    assert XP.fresnel_step_holds(near)
    focus = _doublet_estimate(34.5, 17.25)
    assert XP.fresnel_step_holds(focus) and focus[0] < 1.0


def test_a_crop_inside_the_rim_rays_ring_is_not_silent(monkeypatch):
    """Where the estimate rejects the Fresnel step and the exact construction does not fit (here its beam limit
    lowered to 8 samples), the PSF call warns and names the way out (a DOE plane nearer the exit pupil)."""
    monkeypatch.setattr(XP, "FALLBACK_ASM_SAMPLES", 8)
    hl = _doublet_on_sensor(40.0, 20.0)
    with pytest.warns(StopEdgeWarning, match="inside the rim rays' ring"):
        with torch.no_grad():
            hl.psf_result(torch.zeros(1, 2, dtype=torch.float64), [0.55], ks=32)


def _ring(radius: float, centre=(0.0, 0.0), k: int = 64) -> torch.Tensor:
    t = torch.arange(k, dtype=torch.float64) * (2 * torch.pi / k)
    return torch.stack([centre[0] + radius * torch.cos(t), centre[1] + radius * torch.sin(t)], -1)[None]


def test_a_crop_inside_the_ring_is_one_the_ring_encloses_and_misses():
    """:func:`crop_inside_ring`: rim rays landing on a 0.6 mm ring round the crop (a defocused sensor) enclose it and
    miss its 0.05 mm reach; a 0.01 mm ring (a focus) lands within it; a ring beside the crop's centre (a coma spot's
    cusp, or a crop off the blur) does not enclose it; the ring's direction does not matter."""
    from raywave.hybrid.coherent.stop_edge import crop_inside_ring

    pt = torch.zeros(1, 2, dtype=torch.float64)
    assert bool(crop_inside_ring(_ring(0.6), pt, 0.05))
    assert bool(crop_inside_ring(_ring(0.6).flip(1), pt, 0.05))
    assert not bool(crop_inside_ring(_ring(0.01), pt, 0.05))
    assert not bool(crop_inside_ring(_ring(0.3, (0.4, 0.0)), pt, 0.05))
    assert not bool(crop_inside_ring(_ring(0.6), torch.tensor([[0.9, 0.0]], dtype=torch.float64), 0.05))


def _doublet_reach(sensor: float, plane: float, crop_reach: float):
    from raywave.hybrid.coherent.stop_edge import edge_reach_many

    hl = _doublet_on_sensor(sensor, plane)
    rim = stop_rim_images(hl.lens, (0.0, 0.0), 0.55, None, bound=(hl.doe_z(), XP.EXIT_PUPIL_FAR))
    return edge_reach_many([rim], hl.doe_z(), hl.sensor_z(), torch.zeros(1, 2, dtype=torch.float64), [0.55e-3],
                           crop_reach=crop_reach * hl.crop_reach(32))[0]


def test_the_band_of_a_crop_inside_the_ring_reaches_beyond_the_edge_waves():
    """Class J: on the defocused doublet every rim point's edge wave reaches the crop (on axis as much light as the
    geometric wave), and so does the band's own roll-off: the band reaches DEFOCUS_TAIL_ZONES beyond the edge waves'
    reach, at least DEFOCUS_BAND_ZONES (the 10 mm plane: reach 2.8, band 6.8); in focus the reach is as before."""
    from raywave.hybrid.coherent.stop_edge import DEFOCUS_BAND_ZONES, DEFOCUS_TAIL_ZONES

    plain, wide = _doublet_reach(40.0, 10.0, 0.0), _doublet_reach(40.0, 10.0, 1.0)
    assert 2.0 < plain < 4.0
    assert wide == max(plain + DEFOCUS_TAIL_ZONES, DEFOCUS_BAND_ZONES)
    assert _doublet_reach(34.5, 17.25, 1.0) == _doublet_reach(34.5, 17.25, 0.0)


@pytest.fixture(scope="module")
def defocused_doublet_reference():
    """The rim-image Huygens PSF of the doublet with its sensor at 40 mm (~100 waves past its focus), n_pupil
    converged (its error estimate ~2e-10)."""
    from raywave.models.exit_pupil import huygens_psf

    hl = _doublet_on_sensor(40.0, 10.0)
    with torch.no_grad():
        h = huygens_psf(hl.lens, (0.0, 0.0), 0.55, ks=32, pitch=0.002, n_pupil="auto", sphere="rim_images",
                        max_n_pupil=3072)
    assert h.error_estimate < 1e-6
    return h.psf.squeeze()


def _rel_l1(a, b) -> float:
    return float((a - b).abs().sum() / b.abs().sum())


@pytest.mark.slow
def test_the_default_holds_on_a_sensor_far_from_the_focus(defocused_doublet_reference):
    """Class J: the doublet's sensor 5.5 mm past its focus, its DOE plane 10 mm after the lens: the default (the
    Fresnel step, kept by its estimate, 3.0 zones) 1.9e-4 from the converged Huygens reference with the ring's band
    (2.6e-3 with the in-focus band of 5 zones). Slow (~17 s, most of it the reference's convergence); the default
    suite checks the band's rule (test_the_band_of_a_crop_inside_the_ring_reaches_beyond_the_edge_waves)."""
    hl = _doublet_on_sensor(40.0, 10.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", StopEdgeWarning)
        with torch.no_grad():
            r = hl.psf_result(torch.zeros(1, 2, dtype=torch.float64), [0.55], ks=32)
    err = _rel_l1(r.psf.squeeze(), defocused_doublet_reference)
    print(f"defocused doublet, 10 mm plane: default {err:.2e}")
    assert err < 1e-3


@pytest.mark.slow
def test_the_exact_step_takes_over_where_the_fresnel_step_cannot_hold(defocused_doublet_reference):
    """Class J: on the file's plane (half the last gap, 20 mm) the estimate rejects the Fresnel step (4.6 zones; with
    the ring's band it reads 1.44e-3) and the exact construction takes over (a 4 425-sample beam, over "auto"'s 3 072,
    within FALLBACK_ASM_SAMPLES): 1.9e-4 from the converged reference (its rim step's band the ring's: 6.4e-3 with
    the in-focus band), no warning. ~15 s and 2.8 GB."""
    hl = _doublet_on_sensor(40.0, None)
    with warnings.catch_warnings():
        warnings.simplefilter("error", StopEdgeWarning)
        with torch.no_grad():
            fd = hl.doe_fields(torch.zeros(1, 2, dtype=torch.float64), 0.55, crop_reach=hl.crop_reach(32))[0][0]
            r = hl.psf_result(torch.zeros(1, 2, dtype=torch.float64), [0.55], ks=32)
    assert fd.info.edge_step == "asm"
    err = _rel_l1(r.psf.squeeze(), defocused_doublet_reference)
    print(f"defocused doublet, the file's plane: default {err:.2e}")
    assert err < 1e-3


def test_the_exact_step_keeps_room_for_its_rim_step():
    """The exact construction's lattice is coarsened only while its rim step fits before the DOE plane
    (``_room_for_rim_step``): a 2 µm lattice needs a 1.86 mm step at 0.55 µm, a 1 µm one 0.47 mm; with the DOE
    plane 1 mm after the rim images only the finer fits (a sharp edge on the coarse lattice: 1.4e-3 from the wave
    truth on a sensor 8 mm past the focus, tests/test_ideal_lens_truth.py; 5.0e-4 with the rim step)."""
    from raywave.hybrid.coherent.stop_edge import RimImages

    rim = RimImages(torch.zeros(8, dtype=torch.float64), torch.zeros(8, dtype=torch.float64))
    assert XP._room_for_rim_step(2, rim, (0.0, 1.0), (0.55, 1.0), 1e-3) == 1
    assert XP._room_for_rim_step(2, rim, (0.0, 5.0), (0.55, 1.0), 1e-3) == 2
    assert XP._room_for_rim_step(3, rim, (0.0, 0.5), (0.55, 1.0), 1e-3) == 1  # no room at all: the finest lattice
    assert XP._room_for_rim_step(3, None, (0.0, 0.5), (0.55, 1.0), 1e-3) == 3


def test_the_exact_steps_window_is_measured_on_its_own_plane(monkeypatch):
    """Beyond "auto"'s AUTO_ASM_SAMPLES the fallback measures the exact construction's window on its own plane (the
    rim step's, with the widest band) against FALLBACK_ASM_SAMPLES: the defocused doublet's 4 425-sample beam, a
    5 053² window with the band, fits 6 144; with the limit at 5 000 the beam on the exit-pupil plane would fit but the
    window does not, and the Fresnel step stays (with its warning)."""
    hl = _doublet_on_sensor(40.0, 20.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StopEdgeWarning)
        fits = [XP._exact_step_fits(hl.lens, *_exact_step_args(hl))]
        monkeypatch.setattr(XP, "FALLBACK_ASM_SAMPLES", 5000)
        fits.append(XP._exact_step_fits(hl.lens, *_exact_step_args(hl)))
    assert fits == [True, False]


def _exact_step_args(hl):
    from raywave.hybrid.coherent.geometry import chief_rays
    from raywave.hybrid.coherent.settings import Planes, Source

    wl = 0.55
    z_xp = hl._exit_pupil_planes([wl])[0]
    chief = chief_rays(hl.lens, torch.zeros(1, 2, dtype=torch.float64), torch.tensor([wl], dtype=torch.float64),
                       None, hl.doe_z(), hl.sensor_z())[0][0, 0]
    return (Source((0.0, 0.0), wl, None), (Planes(hl.doe_z(), hl.sensor_z(), z_xp), chief, hl.doe.pitch),
            (None, hl.crop_reach(32)))
