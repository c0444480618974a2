"""Any Pyro model's posterior as a flat log density for :func:`~.nuts.sample_nuts`.

:func:`torch_flat` is the general path of the one sampler: Pyro's own potential energy of the
model (``pyro.infer.mcmc.util.initialize_model``: the same sites, priors and ``biject_to``
transforms Pyro's NUTS samples, TorchScript-compiled when ``jit``), its gradient by autograd,
exposed on a flat unconstrained vector. It serves every configuration the analytic log
densities (:mod:`.fastkoh`, :mod:`.reduced`) do not: a discrepancy GP, custom priors, a local
region's prior, scalar-layout GP emulators, any user model. It is the same posterior Pyro's
NUTS samples by construction; only the trajectory code differs (NumPy instead of Pyro's, ~10x
less overhead per leapfrog step).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pyro
import torch


class TorchFlat:
    """A Pyro model's posterior on a flat unconstrained vector (the :class:`~.fastkoh.FlatModel`
    interface: ``dim``, ``logp_and_grad``, ``to_samples``, ``to_unconstrained``).

    Args:
        model: a Pyro model; args: its arguments.
        jit: compile the potential with TorchScript (falls back to eager if tracing fails).
        seed: Pyro's seed for the prototype trace.
    """

    def __init__(self, model: Callable[..., None], args: tuple = (), jit: bool = True,
                 seed: int = 0) -> None:
        from pyro.infer.mcmc.util import initialize_model

        pyro.set_rng_seed(seed)
        init, pot, self.transforms, _ = initialize_model(model, model_args=args,
                                                         jit_compile=jit,
                                                         skip_jit_warnings=True)
        self._pot = pot
        self.names = list(init)
        self.shapes = [tuple(init[k].shape) for k in self.names]
        self.sizes = [int(np.prod(s)) for s in self.shapes]
        self.offsets = np.concatenate([[0], np.cumsum(self.sizes)]).astype(int)
        self.dim = int(self.offsets[-1])
        self.dtype = next(iter(init.values())).dtype
        self._jit = jit
        self.coord_names = [nm if sz == 1 and not sh else f"{nm}[{i}]"
                            for nm, sz, sh in zip(self.names, self.sizes, self.shapes,
                                                  strict=True) for i in range(sz)]

    def _split(self, q: torch.Tensor) -> dict[str, torch.Tensor]:
        return {k: q[self.offsets[i]:self.offsets[i + 1]].reshape(self.shapes[i])
                for i, k in enumerate(self.names)}

    def logp_and_grad(self, q: np.ndarray) -> tuple[float, np.ndarray]:
        """Log density (Pyro's ``-potential_energy``) and its gradient at ``q (d,)``."""
        qt = torch.tensor(q, dtype=self.dtype, requires_grad=True)
        try:
            pe = self._pot(self._split(qt))
        except torch.linalg.LinAlgError:  # a covariance that is not positive definite there:
            return -math.inf, np.zeros_like(q)  # zero density (as Pyro's potential_grad)
        except RuntimeError:  # TorchScript trouble: Pyro's eager potential
            if not self._jit:
                raise
            self._jit = False
            self._pot = _eager(self._pot)
            return self.logp_and_grad(q)
        if not torch.isfinite(pe):
            return -math.inf, np.zeros_like(q)
        (g,) = torch.autograd.grad(pe, qt)
        return -float(pe.detach()), -g.numpy()

    def to_samples(self, draws: np.ndarray) -> dict[str, torch.Tensor]:
        """Unconstrained draws ``(chain, draw, d)`` -> ``site -> (chain, draw, ...)``
        constrained tensors."""
        out = {}
        lead = draws.shape[:-1]
        for i, k in enumerate(self.names):
            v = torch.as_tensor(draws[..., self.offsets[i]:self.offsets[i + 1]],
                                dtype=self.dtype).reshape(*lead, *self.shapes[i])
            out[k] = self.transforms[k].inv(v).detach() if k in self.transforms else v
        return out

    def to_unconstrained(self, values: dict[str, Any]) -> np.ndarray:
        """``site -> constrained value`` -> the flat vector ``(d,)``."""
        q = np.empty(self.dim)
        for i, k in enumerate(self.names):
            v = torch.as_tensor(values[k], dtype=self.dtype)
            u = self.transforms[k](v) if k in self.transforms else v  # constrained -> unconstrained
            if u.numel() != self.sizes[i]:
                raise ValueError(f"init value of {k} has {u.numel()} elements, expected "
                                 f"{self.sizes[i]}")
            q[self.offsets[i]:self.offsets[i + 1]] = u.detach().reshape(-1).numpy()
        return q


def _eager(pot: Any) -> Any:
    """The eager potential behind a JIT-compiled Pyro potential function."""
    from pyro.infer.mcmc.util import _PEMaker

    maker = getattr(getattr(pot, "func", None), "__self__", None)  # partial(maker._jit, ..)
    if isinstance(maker, _PEMaker):
        maker._compiled_fn = None  # rebuilt lazily, eagerly
        return maker._potential_fn
    return pot


def torch_flat(model: Callable[..., None], args: tuple = (), jit: bool = True) -> TorchFlat:
    """:class:`TorchFlat` of ``model(*args)``."""
    return TorchFlat(model, args, jit)
