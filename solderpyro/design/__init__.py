"""Where the FE runs go: space-filling designs, and the adaptive design that places them where
the surrogate's code uncertainty matters for the calibration (acquisition functions in
BoTorch's interface; the default choice among posterior draws is computed in closed form).

- :mod:`.space_filling`: Latin hypercubes over a parameter box (:func:`lhs`).
- :mod:`.model`: the GPyTorch surrogate as a BoTorch ``Model``.
- :mod:`.acquisition`: acquisition functions (posterior-integrated code variance, and the
  likelihood-aware log-likelihood variance) and the q-batch proposer.
- :mod:`.loop`: the loop fit -> posterior -> FE check -> acquire -> FE, with its stopping rule.

A new acquisition function goes in :mod:`.acquisition` (an ``AcquisitionFunction``
subclass, ``forward(X (b, q, d)) -> (b,)``, built on first use there so that importing the
package does not import BoTorch) and a name in ``CRITERIA``.
"""

from solderpyro.design.space_filling import lhs

__all__ = ["lhs"]
