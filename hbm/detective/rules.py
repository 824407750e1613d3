"""The detective's fixed numbers: decision thresholds, false-alarm rate, band, budgets.

One module that every step reads, so that a threshold is changed in one place
(DESIGN.md §2 explains each value).
"""

from __future__ import annotations

from ..likelihood.collapsed.sampling import CollapsedRoute

# --- decision (DESIGN.md §2: ΔBIC ≈ 6 raised false alarms on AR(1) noise, ≈ 10 did not)
DELTA_LOGZ_MIN = 5.0      # evidence gain needed to name anything (≈ ΔBIC 10)
RUNNER_UP_MARGIN = 3.0    # a named effect must beat the runner-up by this many nats (and 2 SE)
#: a generic shape's gain is a sign of misfit on its own (without a significant misfit window)
#: only above this: its evidence is not corrected for looking everywhere (its position is
#: multimodal; the Laplace/TMCMC estimate credits one mode), while the window scan is calibrated
#: family-wise.  A bump gaining 8.1 nats in the toe of a clean 200-point iid curve (no window) was
#: a false alarm; an out-of-library rupture found by a bump alone gained 28.5 (validation rupture_2)
CONTROL_ALONE_MIN = 2 * DELTA_LOGZ_MIN
REMOVE_TOL = 3.0          # "explains the misfit about as well as the best control": within this many nats of its max log L

# --- where it fails
WINDOW_ALPHA = 0.05       # family-wise false-alarm rate of the misfit-window scan
BAND = 0.90               # posterior-predictive band used for coverage

# --- what is missing
CONTROL_NAME = "local_misfit"
MIN_REFIT_SCORE = 1.0     # screen z below which a candidate is not refitted
N_CONTROL_REFITS = 2      # controls refitted (the best always, the next when its screen is remarkable)
#: a physical refit whose CMA-ES likelihood gain over the base stays at or below this gets no
#: evidence run: its gain (capped by the likelihood gain, decision.gain) cannot reach
#: DELTA_LOGZ_MIN, so it can be neither named nor tied; the Laplace estimate is reported instead.
#: Half the threshold leaves room for an evidence run finding a better optimum than CMA-ES
EVIDENCE_RUN_MIN_GAIN = DELTA_LOGZ_MIN / 2
MAX_EFFECTS = 3           # greedy additions of diagnose (each with the same rule, re-screened)
SCREEN_STEPS = (1e-4, 0.1, 0.3)  # derivative and secant steps (fractions of the box width)

# --- evidence runs
TMCMC_MAX_STEPS = 25      # MH steps per stage cap: the time budget of a diagnosis (≤ 60 s)
TMCMC_MIN_SAMPLES = 250
# decisive comparisons (naming hinges on the evidence, refits.to_refine) are rerun, base and refit
# alike, with the local-covariance random walk (hbm.samplers.local_proposal) and twice the step cap:
# at 25 steps of the global walk the late stages of the larger model stay under-mixed and its log Z
# low.  Measured on the qlv>offset dev case (base + viscoelastic vs + offset, N 800, 6 seeds each,
# mean ± sd of Δlog Z; results/detective_validation.md): global walk 1.9 ± 3.5 at 25 steps, 4.1 ± 0.9
# at 100, 5.2 at 400 (one seed); local walk 2.9 at 25 (two seeds), 5.6 ± 1.4 at 50, 5.4 ± 0.8 at 100.
# 50 local steps reach the converged mean at half the cost of 100 (the reported SE × TMCMC_SE_FACTOR,
# 1.7, covers their scatter); the stages still run to the cap (the decorrelation criterion is not met)
TMCMC_REFINE_STEPS = 50
TMCMC_REFINE_MOVE = "local"
# the collapsed tier (issue 27; Fitter.collapsed): where a model's amplitudes integrate exactly, its
# evidence run samples only the nonlinear and noise parameters: a small TMCMC run and an importance
# finish (hbm.likelihood.collapsed's pilot settings).  On validation case qlv_0 (three rates, 105 points), base +
# viscoelastic, iid, seeds 0-2: the full-space 25-step run gave log Z 493.4 / 500.3 / 496.9 (2 s
# CPU each), this 502.96 / 502.93 (finish accepted, 1.7 s) and one refusal; qlv_1: full 427.0 /
# 424.4 / 422.9, this 427.64 / 427.66 / 427.62.  300 particles × 4 steps + 4000 draws was refused
# in 7 of 9 such runs.  A refused finish (k̂ > 0.7 or ESS < 200) is followed by a collapsed TMCMC run
# of fallback_samples particles with ≤ fallback_steps steps per stage.  On the
# 90-point QLV case of tests/test_detective_tiers.py (finish refused in 3/3 seeds; long full-space
# runs, N 2000 ≤ 100 steps: 420.8, 419.7): N 400 ≤ 10 steps 418.5 / 418.7 / 417.3 (low), N 400
# ≤ 25 steps 420.3 / 420.3 (7.5 s CPU), N 800 ≤ 25 steps 420.7 / 420.2 (15 s)
COLLAPSED_ROUTE = CollapsedRoute(
    pilot_samples=500, pilot_capped=False, pilot_steps=5, importance_draws=10_000, draws_per_sample=0,
    fallback_samples=400, fallback_steps=25, fallback_seed_offset=1, keep_pilot_info=False,
    accepted_route="TMCMC N={pilot} (≤ {steps} steps/stage) + importance finish ({draws} draws)",
    refused_route="importance finish of the small run refused ({reason}); TMCMC N={n} (≤ {steps} steps/stage)")
#: integrated columns above which "auto" keeps the full tier (3: ~0.07 ms per evaluation of the
#: 150-point record; 4, e.g. base + offset: ~2 ms, a minute per run against a second in full)
COLLAPSED_MAX_COLUMNS = 3
TMCMC_SE_FACTOR = 2.5     # reported SE × this covers the seed-to-seed scatter of Δlog Z (12 seeds, README)
MIN_POINTS = 5            # the smallest curve diagnose/extend accept (as hbm fit)
FEW_POINTS = 10           # below this a one-line warning says the detective has little power
PASSIVE_STRESS_RANGE = (1e-3, 2.0)  # MPa: what passive muscle reaches (a file far outside: wrong units)

# --- detection power (hbm diagnose --power)
POWER_REPLICATES = 200    # noise replicates per effect strength (linearised refits, vectorised)
POWER_LEVEL = 0.8         # share of replicates in which an effect must be named at its detection limit
