"""Importing solderpyro leaves a host's GPyTorch as it was.

Other torch projects import this package beside their own GPs: its exact linear algebra
(Cholesky up to 4,096 rows, no fast solves) is a context around its own fits
(:func:`solderpyro.surrogate.exact_linear_algebra`), never a process-wide default. Each test runs
a fresh interpreter: it reads every GPyTorch and linear_operator setting and a host's GP
prediction, imports every solderpyro module (``pkgutil.walk_packages``), and reads both again.
The host's GP has 1,000 training points, above GPyTorch's default ``max_cholesky_size`` (800),
so its posterior mean comes from conjugate gradients; with the exact settings it would come
from a Cholesky factor, and differ (checked, so the comparison can see a change).
"""

import json
import subprocess
import sys

_HOST = r"""
import importlib, inspect, json, pkgutil, sys
import torch
if sys.argv[1] == "botorch":
    import botorch  # noqa: F401  (a BoTorch host: BoTorch's import sets its defaults)
else:
    sys.modules["botorch"] = None  # a host without BoTorch: modules that need it are skipped
import gpytorch
import linear_operator


def settings():
    out = {}
    for mod in (gpytorch.settings, linear_operator.settings):
        for name, cls in sorted(vars(mod).items()):
            if not inspect.isclass(cls):
                continue
            for k in dir(cls):  # inherited ones too (a context's exit sets its own _state)
                if k in ("_default", "_state") or k.startswith("_global"):
                    out[f"{mod.__name__}.{name}.{k}"] = repr(getattr(cls, k))
    return out


class Host(gpytorch.models.ExactGP):
    def __init__(self, x, y):
        super().__init__(x, y, gpytorch.likelihoods.GaussianLikelihood())
        self.mean_module = gpytorch.means.ConstantMean()
        self.covar_module = gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel())

    def forward(self, x):
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x),
                                                         self.covar_module(x))


def predict():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1000, 1, generator=g, dtype=torch.float64)
    y = torch.sin(6 * x[:, 0]) + 0.1 * torch.randn(1000, generator=g, dtype=torch.float64)
    m = Host(x, y).double()
    m.covar_module.base_kernel.lengthscale = 0.2
    m.likelihood.noise = 0.01
    m.eval()
    torch.manual_seed(0)
    with torch.no_grad():
        return m(torch.linspace(0, 1, 50, dtype=torch.float64)[:, None]).mean


s0, p0 = settings(), predict()
with gpytorch.settings.max_cholesky_size(4096), \
        gpytorch.settings.fast_computations(False, False, False):
    exact = predict()
import solderpyro
skipped = []
for info in pkgutil.walk_packages(solderpyro.__path__, "solderpyro."):
    try:
        importlib.import_module(info.name)
    except ImportError as e:
        if "botorch" not in str(e):
            raise
        skipped.append(info.name)
s1, p1 = settings(), predict()
print(json.dumps({"changed": {k: [s0[k], s1.get(k)] for k in s0 if s0[k] != s1.get(k)},
                  "new": sorted(set(s1) - set(s0)), "n_settings": len(s0),
                  "same_prediction": bool(torch.equal(p0, p1)),
                  "exact_moves_it": float((exact - p0).abs().max()),
                  "skipped": skipped, "n_modules": len(list(pkgutil.walk_packages(
                      solderpyro.__path__, "solderpyro.")))}))
"""


def _host(kind: str) -> dict:
    out = subprocess.run([sys.executable, "-c", _HOST, kind], capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.splitlines()[-1])


def test_importing_solderpyro_changes_no_gpytorch_setting_of_a_host_without_botorch():
    """A host without BoTorch: every solderpyro module that does not need BoTorch imported
    (those that do are the design's BoTorch models, and only they are skipped), and no
    GPyTorch or linear_operator setting changed, nor the host's GP prediction, to the bit."""
    r = _host("plain")
    assert r["n_settings"] > 30
    assert r["changed"] == {} and r["new"] == []
    assert r["same_prediction"]
    # the host's GP is one the settings matter to: exact solves move its mean by far more
    # than rounding (conjugate gradients stop at a tolerance of ~1e-3 relative)
    assert r["exact_moves_it"] > 1e-8
    assert r["skipped"] and all(m.startswith("solderpyro.design.") for m in r["skipped"])
    assert len(r["skipped"]) <= 3 < r["n_modules"]


def test_importing_solderpyro_changes_no_gpytorch_setting_of_a_botorch_host():
    """A host that imported BoTorch (and so has BoTorch's defaults): every solderpyro module
    imported, and no setting changed, nor the host's GP prediction."""
    r = _host("botorch")
    assert r["skipped"] == []
    assert r["changed"] == {} and r["new"] == []
    assert r["same_prediction"]
