"""Fabrication tolerance of an L = 2^k level DOE: etch-depth errors and mask misalignment, by Monte Carlo.

**The fabricated profile.** An L-level DOE is made with k binary masks (:mod:`raywave.doe.fabrication`): step j
(j = 1..k) etches the areas open in mask j by ``d_j = h_2π/2^j``. A fabricated element deviates from the design
in two ways, modelled here per mask (= per lithography + etch step):

* **etch depth**: step j etches ``d_j (1 + ε_j)``: one relative error ε_j per step, the same over the whole
  element (an etch-rate / time error);
* **misalignment**: mask j lies shifted by ``(δx_j, δy_j)`` DOE pixels on the substrate (the pattern moves
  toward +x for δx > 0: ``m_j(x − δx_j, y − δy_j)``); mask 1 is the reference (δ_1 = 0), so only relative
  shifts count, as in a real layer-to-layer alignment.

The relief height above the deepest floor, in units of ``h_2π/L`` ("level units"), is then

    h(x, y) = Σ_j 2^(k−j) (1 + ε_j) (1 − m_j(x − δx_j, y − δy_j)),

which is the level map ℓ exactly when every ε_j and δ_j is zero (Σ_j 2^(k−j) = L − 1: level L − 1 is the
unetched top). The phase at any wavelength follows the DOE's material dispersion (:class:`~raywave.doe.DOE`
``dispersion="material"``): ``φ(λ) = 2π α(λ) h / L`` with ``α(λ) = λ0 (n(λ) − n_m) / (λ (n(λ0) − n_m))``.

**Sub-pixel shifts, exactly.** Misalignment is a fraction of a pixel. On a grid of q × q samples per DOE pixel
(the ray-wave simulation grid of a :class:`~raywave.hybrid.HybridLens` with ``oversample=q``; q = 1 is the DOE
grid), every sample is split at the fractional parts of the k masks' shifts into at most (k+1)² sub-rectangles on
each of which every shifted mask, hence the relief, is constant (:func:`profile_parts`). So the fabricated,
sharp-edged staircase is represented without approximation: its **mean transmittance** over each sample
(:func:`transmittance`, ``|t| < 1`` on samples that an edge crosses: the exact cell average of ``exp(iφ)``, what
diffraction into angles resolved by the grid sees) and its mean height (:func:`level_height`). Outside the DOE
grid nothing is etched: a shifted mask drags unetched field into the grid's edge (``periodic=True`` wraps
instead, for whole periods of a grating). Representing an edge inside a sample by the mean *height* instead
(a one-sample ramp) or rounding the shifts to whole samples would bias η₁ by ≈ 0.1/q or scatter it by ≈ 0.15/q
for ±0.25 px (measured on a 16-level grating), which is why neither is done.

**Efficiency.** Scalar, thin-element theory:

* a **grating** (one period of a 1-D blazed staircase, one level per pixel, periodic): the Fourier coefficient
  of order m of the perturbed period's transmittance ``exp(iφ)``, computed exactly from its piecewise-constant
  segments (:func:`grating_efficiency`, any shifts), or by an FFT of the period's sample-averaged transmittance on
  the q-times oversampled grid, ``η_m = |FFT_m/N|² sinc²(m/N)`` (:func:`grating_efficiency_fft`; the sinc is the
  exact integral of a constant sample, so the FFT is exact when the shifts are whole samples);
* a **general DOE**, relative to its design: the power fraction of the design's order-m wave
  ``exp(i m φ_u)`` (φ_u: the unwrapped, unquantised design phase at λ0; order m of a kinoform wrapped on φ_u is
  ``exp(i m φ_u)`` at every wavelength), the normalised overlap over the aperture A

      η_m = |∫_A exp(iφ_pert) exp(−i m φ_u) dA|² / A²     (:func:`doe_efficiency`),

  with φ_u linear inside each DOE pixel (its gradient from wrapped central differences) and the design wave
  integrated exactly over each sub-rectangle (``sinc(m g_x du/2πq) · sinc(m g_y dv/2πq)`` about its centre), so
  the overlap is exact for any shifts. For a linear grating over whole periods it *is* the grating's order-m
  efficiency (sinc²(1/L) for a nominal L-level staircase; the same digits as :func:`grating_efficiency` with
  errors): tested. For m ≡ 1 (mod L) at λ0 it holds pixel by pixel, so any width will do. ``relative`` is the
  overlap with the *nominal* fabricated element instead (1 without errors).

**Random errors** (:func:`sample_errors`): a tolerance ``±x`` is read as **±2σ of a normal distribution**
(``distribution="normal"``, the default: σ = x/2, 95 % of the samples inside ±x) or as the bounds of a
**uniform** one (``distribution="uniform"``). ``depth_error`` x is in percent of each step's depth (independent
per step); ``misalignment`` in DOE pixels, independent in x and y for every mask but the first. Random numbers
come from a CPU ``torch.Generator`` (``seed`` or ``generator``) in a fixed order, so a seed reproduces a run
exactly on any device.

**PSF** (:func:`raywave.assembly.tolerance.tolerance_monte_carlo`, in the assembly layer above
:mod:`raywave.hybrid`; this module's loop tells it about every draw through an ``observer``). With ``lens`` (a
:class:`~raywave.hybrid.HybridLens`) every sample's perturbed element replaces the DOE and
the ray-wave PSF is compared with the nominal element's (the field arriving at the DOE depends on the lens only
and is computed once). The element enters as its sample-averaged transmittance on the lens's simulation grid
(``oversample``): its phase through :meth:`PerturbedDOE.phase`, its amplitude (< 1 on samples that a shifted
edge crosses) multiplied into the incident field. PSFs are kept as **fractions of the power incident on the
DOE** (not renormalised to 1, so that light a fabrication error sends into other orders, out of the crop, counts):
``peak_ratio`` = peak / nominal peak (Strehl-like), ``l1`` = Σ|p − p0| / Σ p0, ``crop_energy`` = Σ p, and the
shape metrics ``rms_radius_um`` and ``r80_um`` of :func:`raywave.hybrid.metrics.psf_metrics`. Tested: the in-focus
peak of a diffractive lens follows η₁ (the other orders are out of focus).
"""

# The model is split by concern (issue 17): errors (FabricationErrors, sample_errors), profile (the exact
# perturbed profile, PerturbedDOE), gratings, overlap (a general DOE's efficiency), monte_carlo (the loop,
# ToleranceResult). Every name stays importable from here.
from raywave.doe.tolerance.errors import DISTRIBUTIONS, FabricationErrors, sample_errors
from raywave.doe.tolerance.gratings import blazed_grating_levels, grating_efficiency, grating_efficiency_fft
from raywave.doe.tolerance.monte_carlo import PSF_METRICS, ToleranceResult, summary_stats, tolerance_monte_carlo
from raywave.doe.tolerance.overlap import ToleranceWarning, design_maps, doe_efficiency
from raywave.doe.tolerance.profile import PerturbedDOE, level_height, profile_parts, transmittance

__all__ = ["DISTRIBUTIONS", "PSF_METRICS", "FabricationErrors", "PerturbedDOE", "ToleranceResult", "ToleranceWarning",
           "blazed_grating_levels", "design_maps", "doe_efficiency", "grating_efficiency", "grating_efficiency_fft",
           "level_height", "profile_parts", "sample_errors", "summary_stats", "tolerance_monte_carlo",
           "transmittance"]
