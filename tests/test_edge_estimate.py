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
    """A beam over AUTO_ASM_SAMPLES on the exit-pupil plane (here the limit lowered to 8 samples): the Fresnel step
    with a StopEdgeWarning naming the estimate and edge_step='asm'."""
    monkeypatch.setattr(XP, "AUTO_ASM_SAMPLES", 8)
    hl = lens_a_hybrid(7.0)
    with pytest.warns(StopEdgeWarning, match=r"error estimate.*edge_step='asm'"):
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
    much farther from the rim: on the file's plane (half the gap, 20 mm) the Fresnel step reads 1.38e-1 from the
    converged Huygens reference (benchmarks/defocused_sensor.py), and the estimate now rejects it (4.6 zones; the
    crop's reach alone: 0.34); on a plane 5 mm after the lens, 3.3e-4 from it, the estimate keeps it; in focus (34.5
    mm, 1.75e-4) the estimate is the crop's reach alone, as before."""
    far, near = _doublet_estimate(40.0, 20.0), _doublet_estimate(40.0, 5.0)
    assert not XP.fresnel_step_holds(far) and far[0] > 4.0
    assert XP.fresnel_step_holds(near)
    focus = _doublet_estimate(34.5, 17.25)
    assert XP.fresnel_step_holds(focus) and focus[0] < 1.0


def test_a_crop_inside_the_rim_rays_ring_is_not_silent():
    """Where the estimate rejects the Fresnel step and the exact construction does not fit (the doublet's beam on its
    exit-pupil plane), the PSF call warns and names the way out (a DOE plane nearer the exit pupil, or
    edge_step='asm': 6.4e-3 from the reference there); before class J's rule it was silent."""
    hl = _doublet_on_sensor(40.0, 20.0)
    with pytest.warns(StopEdgeWarning, match="inside the rim rays' ring"):
        with torch.no_grad():
            hl.psf_result(torch.zeros(1, 2, dtype=torch.float64), [0.55], ks=32)
