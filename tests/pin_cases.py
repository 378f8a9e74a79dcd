"""The PSF pin cases of tests/test_psf_pins.py (issue 17: refactors must not change the numerics).

Each case builds a hybrid lens and the arguments of one ``HybridLens.psf_result`` call. The reference PSFs in
tests/data/psf_pins.npz were computed with these cases from the code at commit 17ade15 (before the issue-17
refactor); regenerate them (``python tests/pin_cases.py``) only for a deliberate, documented numeric change.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

PINS = Path(__file__).resolve().parent / "data" / "psf_pins.npz"


def _hybrid_asphere(**kw):
    """The bundled hybrid lens; the pins before issue 19's default flip were computed with the DOE-plane edge and
    the exact ("auto") exit-pupil step, so the cases name them."""
    from raywave.assembly.build import load_hybrid
    from raywave.lens.build import bundled_lens_path

    kw.setdefault("stop_edge", "doe")
    if kw["stop_edge"] == "exit_pupil":
        kw.setdefault("edge_step", "auto")
    return load_hybrid(bundled_lens_path("hybrid_asphere"), **kw)


def _fresnel_on_asphere():
    """hybrid_asphere with a 16-level Fresnel DOE (f = 200 mm, fused silica) on a 1.2 mm grid."""
    from raywave.doe.params import FresnelDOE
    from raywave.hybrid.hybrid_lens import HybridLens

    hl = _hybrid_asphere()
    doe = FresnelDOE(200.0, (1200, 1200), 1e-3, material="FUSED_SILICA")
    doe.fabricate(levels=16)
    return HybridLens(hl.lens, doe, hl.doe_distance, sensor_pitch=hl.sensor_pitch, stop_edge="doe")


def _cooke():
    from raywave.assembly.build import load_hybrid
    from raywave.lens.build import bundled_lens_path

    return load_hybrid(bundled_lens_path("cooke_triplet"), doe_pitch=4e-3, sensor_pitch=4e-3, stop_edge="doe")


def _ideal_exit_pupil():
    from raywave.doe.params import Binary2DOE
    from raywave.hybrid.hybrid_lens import HybridLens
    from raywave.lens.build import ideal_lens

    lens = ideal_lens(20.0, f_number=8, wavelengths=(0.55,))
    doe = Binary2DOE([-5.0, 1.0], 1.0, (800, 800), 2e-3)
    return HybridLens(lens, doe, 10.0, sensor_pitch=2e-3, stop_edge="exit_pupil", edge_step="auto")


#: name -> (builder, psf_result kwargs). The two exact-construction cases (``hybrid_asphere_exit_pupil``,
#: ``ideal_binary2_exit_pupil``: ``edge_step="auto"`` takes "asm" for these beams) were re-pinned on 2026-11-28 when
#: that construction moved its edge from the exit-pupil plane to the stop's rim images (issue 19; on axis the two
#: agree to L1 3e-5, at 17.5° the rim images bring the bundled asphere from 2.0e-3 to 5.9e-4 of the Huygens PSF);
#: with ``hybrid_asphere_default`` (the Fresnel step) again the same day, when the step's Fresnel parameter came
#: from each node's optical path difference to the edge (17.5°: 4.3e-3 -> 2.0e-3 from Huygens).
#: ``cooke_triplet`` and ``ideal_binary2_exit_pupil`` (sensor pixels of the DOE's pitch) were re-pinned on 2026-11-29
#: (issue 47) when the engine's pixel quadrature began refining itself (``integrated_upsampled_intensity(refine=True)``:
#: q = 8 where q = 4 leaves more than 2e-4): rel L1 2.1e-3 and 3.3e-4 (benchmarks/results/
#: psf_pins_refine_2026-11-29_j47.json has every pin's old-vs-new difference; the others move by < 1e-11).
#: ``hybrid_asphere_exit_pupil`` (slow) was re-pinned on 2026-11-29: stale since 284053a (it differed already at the
#: commit that regenerated the pins); rel L1 8.8e-5 (benchmarks/results/psf_pin_slow_exit_pupil_2026-11-29.json).
#: ``hybrid_asphere_default``, ``hybrid_asphere_exit_pupil`` and ``ideal_binary2_exit_pupil`` were re-pinned on
#: 2026-11-29 (issue 47, k47) when the Fresnel edge step began reading the stop rim's images by trigonometric
#: interpolation (raywave.hybrid.coherent.stop_edge._rim_fourier): rel L1 1.9e-4, 4.8e-5 and 1.4e-5; the others moved
#: by < 1e-11 (benchmarks/results/psf_pins_rim_fourier_2026-11-29_k47.json).
#: ``hybrid_asphere_default``, ``ideal_binary2_exit_pupil`` and ``hybrid_asphere_exit_pupil`` were re-pinned on
#: 2026-12-01 (issue 47's cost, h47c) when the ripple band began to narrow where the edge waves' reach is short
#: (stop_edge.short_reach_band): rel L1 4.3e-5 / 7.9e-6, 7.0e-6 / 6.9e-6 and 7.5e-6; the others bit for bit
#: (benchmarks/results/stop_edge_band_accuracy_2026-12-01_xxvii_h47c.json, with the references' figures).
CASES = {
    "hybrid_asphere": (_hybrid_asphere, dict(fields=[(0.0, 0.0), (0.0, 7.0), (0.0, 14.0), (3.0, 10.0)],
                                             wavelengths=[0.47, 0.53, 0.66], ks=32)),
    "hybrid_asphere_fresnel": (_fresnel_on_asphere, dict(fields=[(0.0, 0.0), (0.0, 3.0)],
                                                         wavelengths=[0.47, 0.66], ks=32)),
    "hybrid_asphere_exit_pupil": (lambda: _hybrid_asphere(stop_edge="exit_pupil"),
                                  dict(fields=[(0.0, 14.0)], wavelengths=[0.53], ks=32)),
    # the default since issue 19 (the exit-pupil edge, Fresnel step); pinned from commit 2026-11-26 (issue 19)
    "hybrid_asphere_default": (lambda: _hybrid_asphere(stop_edge=None),
                               dict(fields=[(0.0, 0.0), (0.0, 14.0)], wavelengths=[0.53], ks=32)),
    "hybrid_asphere_faithful": (_hybrid_asphere, dict(fields=[(0.0, 7.0)], wavelengths=[0.53], ks=32,
                                                      mode="faithful", rays=20000, seed=1)),
    "cooke_triplet": (_cooke, dict(fields=[(0.0, 0.0), (0.0, 14.0)], wavelengths=[0.5875618], ks=24)),
    "ideal_binary2_exit_pupil": (_ideal_exit_pupil, dict(fields=[(0.0, 0.0), (0.0, 2.0)], wavelengths=[0.55],
                                                         ks=32)),
}


def compute(name: str, device: str = "cpu") -> dict[str, np.ndarray]:
    """PSF, centre and energy outside of one case, as numpy arrays."""
    import warnings

    build, kw = CASES[name]
    kw = dict(kw)
    seed = kw.pop("seed", None)
    hl = build().to(device)
    if seed is not None:
        # a CPU generator on every device: the ray sample is drawn where the generator lives, then moved, so
        # the GPU traces the same rays (a CUDA generator's Philox stream is another sample)
        kw["generator"] = torch.Generator().manual_seed(seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with torch.no_grad():
            r = hl.psf_result(**kw)
    return {"psf": r.psf.cpu().numpy(), "center": r.center.detach().cpu().numpy(),
            "energy_outside": r.energy_outside.detach().cpu().numpy()}


if __name__ == "__main__":
    import sys
    import time

    # python tests/pin_cases.py [NAME ...]: recompute those cases only (default: all), keeping the other pins
    names = sys.argv[1:] or list(CASES)
    out = dict(np.load(PINS)) if PINS.exists() and sys.argv[1:] else {}
    for name in names:
        t = time.time()
        for k, v in compute(name).items():
            out[f"{name}/{k}"] = v
        print(f"{name}: {time.time() - t:.2f} s")
    np.savez_compressed(PINS, **out)
    print(f"wrote {PINS} ({PINS.stat().st_size / 1e3:.0f} kB)")
