"""Organ-scale prediction: force–elongation of a fusiform muscle from constitutive parameters.

A reduced-order *slender-body* model replaces the axisymmetric finite-element model of the
thesis (§3.3.2, Figs. 3.64–3.66).  The muscle belly of reference length ``L`` has a circular
cross-section of reference radius ``R(z)``, ``0 ≤ z ≤ L``, and carries tendons in series at
both ends.  Under an axial force ``F`` (N) every cross-section carries the same force, and the
fibers, which run along the axis, are in uniaxial tension.  With incompressibility the current
area of the section is ``A0(z)/λ(z)``, so equilibrium of each section reads::

    F = σ(λ(z)) · A0(z) / λ(z)   ⇔   P(λ(z)) = σ(λ(z)) / λ(z) = F / A0(z)

where σ is the uniaxial Cauchy stress of the constitutive model (MPa = N/mm²) and P the
nominal (first Piola) stress.  ``λ(z)`` follows from a bracketed, vectorised root find of
this scalar equation for every posterior sample, section and force level at once.  The
organ elongation is::

    δ(F) = ∫₀ᴸ (λ(z) − 1) dz  +  (L_prox + L_dist) · ε_t(F / A_t)

(composite Simpson or trapezoid rule on the section grid) where ε_t is the tendon strain law
(linear ``ε_t = F/(E_t·A_t)`` or a documented toe + linear law, see :class:`FusiformGeometry`).

Units: lengths in mm, areas in mm², forces in N, stresses and moduli in MPa (= N/mm²).

Assumptions and where they break
--------------------------------
* **Slender body, uniaxial stress in every section.**  The radius varies slowly compared with
  the length (|dR/dz| ≪ 1); shear and lateral tractions between neighbouring sections are
  neglected, so each section is in the same uniaxial state as the tested specimen.  This
  breaks near strongly tapered ends (|dR/dz| of order 1, e.g. a short belly with a large
  mid-belly radius) and wherever the stress state is three-dimensional (attachments, grips).
  For the sine profile max |dR/dz| = π(R_mid − R_end)/L; keep it well below 1.
* **Fibers parallel to the axis**; no pennation, no aponeuroses, no fiber curvature.  A
  pennate muscle (e.g. a real rat tibialis anterior) is only approximated by its fusiform
  "equivalent".
* **Incompressible** tissue (the current area is A0/λ), as in the constitutive model.
* **Quasi-static, passive**: no active force; only the *elastic* stage of the model is used
  (see below); no inertia, no rate dependence.
* **The constitutive model's uniaxial curve per section**: the tissue tested on the specimen
  is assumed to represent every section.  Beyond the strains tested on the specimen the curve
  is an extrapolation (:func:`extrapolation_mask`; thesis Fig. 3.64).
* **Tendons in series**, uniform, small-strain (nominal tendon stress F/A_t).
* **Tension only** (F ≥ 0); compression would buckle a slender body.

Only the effects of stage ``"elastic"`` enter the tissue law: kinematics effects (slack,
series compliance of the test rig) and output effects (load-cell offset) describe the test,
not the tissue, and history effects (viscoelasticity, damage) are dropped by the quasi-static
assumption.  Excluded effects are listed in :attr:`OrganResponse.excluded_effects`.

Solver: per sample a table of P on a stretch grid (monotonicity check), then anchor stresses
(log-spaced, common to all samples) solved by bracketed Anderson–Björck regula falsi, then
every (sample, section, force) unknown from a cubic Hermite guess in ln s between two anchors,
one vectorised evaluation, and bracketed polishing of the few that are not yet within ``tol``.
No Python loop runs over samples or sections (only over iterations and memory chunks).

A unique stretch needs a nominal stress P(λ) that increases with λ.  The solver checks P on a
stretch grid for every sample (:attr:`OrganResponse.non_monotone`) and marks force levels that
need a stretch above ``max_stretch`` somewhere in the belly (:attr:`OrganResponse.unreachable`,
elongation NaN), or raises :class:`~hbm.errors.HbmError` with ``strict=True``.
"""

from .geometry import PROFILES, TENDON_LAWS, FusiformGeometry, load_geometry, quadrature_weights
from .response import OrganResponse, extrapolation_mask, force_levels, organ_response, theta_from_samples
from .stretch import nominal_stress, tendon_strain

__all__ = ["FusiformGeometry", "OrganResponse", "load_geometry", "organ_response", "force_levels",
           "extrapolation_mask", "nominal_stress", "tendon_strain", "theta_from_samples", "PROFILES",
           "TENDON_LAWS", "quadrature_weights"]
