"""Importing solderpyro, and running its BoTorch code, leaves a host's GPyTorch as it was.

Other torch projects import this package beside their own GPs. Importing BoTorch sets
process-wide GPyTorch and linear_operator defaults (botorch/__init__.py: Cholesky up to 4,096
rows, 6 jitter tries, no fast solves, log-probabilities or root decompositions, kernels
evaluated eagerly up to 4,096 rows); solderpyro imports BoTorch only where it uses it, in
:func:`solderpyro.surrogate.gp.botorch_imports`, which gives the host its settings back, and
runs its GP computations in :func:`solderpyro.surrogate.exact_linear_algebra` (BoTorch's
values, in a context). Each test runs a fresh interpreter (so that the host has not imported
BoTorch unless it chooses to): it reads every GPyTorch and linear_operator setting (every class
of the two settings modules, so a new setting is covered) and a host's GP prediction, imports
every solderpyro module (``pkgutil.walk_packages``), reads both again, runs solderpyro's
BoTorch code (the discrepancy fit, BoTorch's ``SingleTaskGP`` and ``fit_gpytorch_mll``, and the
design's BoTorch classes), and reads both a third time. A third test reads solderpyro's source:
every BoTorch import in it is in ``with botorch_imports():``.

The host's GP has 1,000 training points, above GPyTorch's default ``max_cholesky_size`` (800),
so its posterior mean comes from conjugate gradients; with BoTorch's settings it would come
from a Cholesky factor, and differ (checked, so the comparison can see a change).
"""

import ast
import json
import subprocess
import sys
from importlib.util import find_spec
from pathlib import Path

_HOST = r"""
import importlib, inspect, json, pkgutil, sys
import numpy as np
import torch
if sys.argv[1] == "botorch":
    import botorch  # noqa: F401  (a BoTorch host: BoTorch's import sets its defaults)
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


def changed(a, b):
    return {k: [a.get(k), b.get(k)] for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)}


s0, p0 = settings(), predict()
with gpytorch.settings.max_cholesky_size(4096), \
        gpytorch.settings.fast_computations(False, False, False):
    exact = predict()
botorch_before = "botorch" in sys.modules
import solderpyro
names = [i.name for i in pkgutil.walk_packages(solderpyro.__path__, "solderpyro.")]
for name in names:
    importlib.import_module(name)
botorch_after_import = "botorch" in sys.modules
s1, p1 = settings(), predict()
# solderpyro's BoTorch code: the discrepancy fit (SingleTaskGP, fit_gpytorch_mll) on a tiny
# residual, and the design's BoTorch classes (defined on first use)
from solderpyro.exact.discrepancy import fit_discrepancy
rng = np.random.default_rng(0)
t = np.linspace(0.0, 1.0, 30)
dis = fit_discrepancy(np.c_[t, np.zeros_like(t)], np.sin(6 * t) + 0.1 * rng.standard_normal(30),
                      noise_sd=0.1)
from solderpyro.design.acquisition import qIntegratedLogLikVariance
from solderpyro.design.model import SurrogateInputs
from botorch.acquisition import AcquisitionFunction
from botorch.models.transforms.input import InputTransform
s2, p2 = settings(), predict()
print(json.dumps({"import_changed": changed(s0, s1), "run_changed": changed(s0, s2),
                  "n_settings": len(s0), "n_modules": len(names),
                  "same_prediction": [bool(torch.equal(p0, p1)), bool(torch.equal(p0, p2))],
                  "exact_moves_it": float((exact - p0).abs().max()),
                  "botorch": [botorch_before, botorch_after_import, "botorch" in sys.modules],
                  "subclasses": [issubclass(qIntegratedLogLikVariance, AcquisitionFunction),
                                 issubclass(SurrogateInputs, InputTransform)],
                  "discrepancy": [dis.sd_um, dis.noise_sd_um, dis.lengthscales.tolist()],
                  "max_cholesky_size": linear_operator.settings.max_cholesky_size.value()}))
"""


def _host(kind: str) -> dict:
    out = subprocess.run([sys.executable, "-c", _HOST, kind], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.splitlines()[-1])


def test_solderpyro_changes_no_gpytorch_setting_of_a_host_without_botorch():
    """A host without BoTorch: every solderpyro module imported, none of them importing BoTorch,
    and no GPyTorch or linear_operator setting changed, nor the host's GP prediction, to the
    bit; then solderpyro's BoTorch code runs (BoTorch imported), and still nothing changed."""
    r = _host("plain")
    assert r["n_settings"] > 30 and r["n_modules"] > 50
    assert r["import_changed"] == {}
    assert r["run_changed"] == {}
    assert r["same_prediction"] == [True, True]
    # the host's GP is one the settings matter to: exact solves move its mean by far more
    # than rounding (conjugate gradients stop at a tolerance of ~1e-3 relative)
    assert r["exact_moves_it"] > 1e-8
    # importing solderpyro imports no BoTorch; its BoTorch code did, and the design's BoTorch
    # subclasses are BoTorch's classes
    assert r["botorch"] == [False, False, True]
    assert r["subclasses"] == [True, True]
    assert r["max_cholesky_size"] == 800  # GPyTorch's own default, not BoTorch's


def test_solderpyro_changes_no_gpytorch_setting_of_a_botorch_host():
    """A host that imported BoTorch (and so wants BoTorch's defaults): importing every
    solderpyro module and running its BoTorch code leaves them, and the host's GP prediction,
    as they were; and the discrepancy fit is the same as in a host without BoTorch (it runs
    in BoTorch's settings either way)."""
    r = _host("botorch")
    assert r["import_changed"] == {}
    assert r["run_changed"] == {}
    assert r["same_prediction"] == [True, True]
    assert r["botorch"] == [True, True, True]
    assert r["max_cholesky_size"] == 4096  # BoTorch's default, as the host set it
    plain = _host("plain")
    assert r["discrepancy"] == plain["discrepancy"]


def _botorch_imports_outside_the_helper(tree: ast.AST) -> list[int]:
    """Lines of ``import botorch...`` statements that are neither in a
    ``with botorch_imports():`` block nor in an ``if TYPE_CHECKING:`` block."""
    out: list[int] = []

    def visit(node: ast.AST, guarded: bool) -> None:
        for child in ast.iter_child_nodes(node):
            g = guarded
            if isinstance(child, ast.With):
                g = g or any(isinstance(i.context_expr, ast.Call) and ast.unparse(
                    i.context_expr.func).split(".")[-1] == "botorch_imports" for i in child.items)
            if isinstance(child, ast.If) and ast.unparse(child.test).endswith("TYPE_CHECKING"):
                g = True
            if isinstance(child, ast.Import | ast.ImportFrom) and not g:
                names = ([a.name for a in child.names] if isinstance(child, ast.Import)
                         else [child.module or ""])
                if any(n == "botorch" or n.startswith("botorch.") for n in names):
                    out.append(child.lineno)
            visit(child, g)

    visit(tree, False)
    return out


def test_solderpyro_imports_botorch_only_in_botorch_imports():
    """Every BoTorch import in solderpyro's source is in ``with botorch_imports():`` (or only
    for type checking): the first import of BoTorch in a process runs BoTorch's
    ``__init__``, wherever it happens, so each one must give the host its settings back."""
    spec = find_spec("solderpyro")
    assert spec is not None and spec.submodule_search_locations
    root = Path(list(spec.submodule_search_locations)[0])
    bad = {str(p.relative_to(root)): lines for p in sorted(root.rglob("*.py"))
           if (lines := _botorch_imports_outside_the_helper(ast.parse(p.read_text())))}
    assert bad == {}
