"""``viscoelastic_2``, ``viscoelastic_3``: a second and a third relaxation time, once one is in the model.

Tissue relaxes with more than one time constant (muscle: seconds and minutes).  Each further
time is the same quasi-linear relaxation again, with its own relaxing fraction and time constant,
applied to the stress the model already relaxes::

    σ = G_k ⊛ (… G_1 ⊛ σ_e),    G_k(t) = 1 − g_k·(1 − exp(−t/τ_k))

(⊛: the hereditary integral of :class:`~hbm.effects.viscoelastic.Viscoelastic`).  The composition
of Prony relaxations is again a Prony series in the same time constants -- in the Laplace domain
the product of (g∞ᵢ + gᵢ·s/(s + 1/τᵢ)) is a constant plus one term per time constant -- so
``viscoelastic`` + ``viscoelastic_2`` is a two-term Prony series whose weights follow from
G1 and G2 (``viscoelastic_2`` at G2 = 0 is the one-term model, nested as the detective needs).
Its length is picked by the evidence, one term at a time: ``viscoelastic_2`` is a candidate only
when the model has ``viscoelastic`` (``requires``), ``viscoelastic_3`` only beside
``viscoelastic_2`` -- in ``hbm diagnose`` (greedy rounds), ``hbm extend --add`` and ``--power``.
"""

from __future__ import annotations

from .viscoelastic import Viscoelastic


class SecondRelaxation(Viscoelastic):
    """A second relaxation time, applied to the stress the first one relaxes (module docstring).

    Parameters
    ----------
    G2 : -, box [0, 0.9], null 0
        Relaxing fraction of the second term.
    LOGTAU2 : log10 s, box [−1, 3.5], null 2 (a placeholder while G2 = 0)
        Its time constant; passive muscle relaxes over seconds to minutes (Van Loocke M, Lyons CG,
        Simms CK 2008, J Biomech 41:1555–1566).
    tau : float, optional (constructor)
        Fix the time constant in seconds instead of inferring LOGTAU2.
    """

    name = "viscoelastic_2"
    first = 2
    strength = "G2"
    requires = ("viscoelastic",)
    description = "a further relaxation time (Prony term, QLV) of a viscoelastic tissue"

    def __init__(self, tau=None) -> None:
        super().__init__(terms=1, tau=tau)


class ThirdRelaxation(SecondRelaxation):
    """A third relaxation time, beside the second (module docstring).

    Parameters
    ----------
    G3 : -, box [0, 0.9], null 0
    LOGTAU3 : log10 s, box [−1, 3.5], null 3
    """

    name = "viscoelastic_3"
    first = 3
    strength = "G3"
    requires = ("viscoelastic_2",)
