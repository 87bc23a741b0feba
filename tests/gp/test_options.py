"""The front door's named choices (``gp.options``): ``MapPrior`` and ``Engine`` build the same model as the former
flat keywords, which still work with one DeprecationWarning naming the new spelling at the caller's line; the
library's own code and experiments use the new spelling only."""

from __future__ import annotations

import ast
import json
import warnings
from pathlib import Path

import pytest
import torch

import irft_torch as irft
from irft_torch.gp.options import Engine, MapPrior, grouped
from irft_torch.studies import calibration as cal

ROOT = Path(__file__).resolve().parents[2]
FLAT = {"li_basis", "generic_shape", "prior_mean", "priors", "tied_noise", "lengthscale", "method", "tol", "solver",
        "dtype", "max_harmonics", "surface_offset", "surface_groups"}


@pytest.fixture(scope="module")
def data():
    truth, _ = cal.medium("presets", 0)
    c = cal.motion("short", 0)
    return c, cal.simulate(truth, c, 0.02, 0)


def _quiet(*args, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return irft.InverseRFT(*args, **kw)


# (former flat keywords, the new spelling, the resolved MapPrior / Engine fields expected, written out by hand)
CASES = [
    ({"li_basis": False}, {"prior": MapPrior(kernel="rbf")}, {"kernel": "rbf"}, {}),
    ({"li_basis": True, "generic_shape": True}, {"prior": MapPrior(kernel="li+generic")}, {"kernel": "li+generic"}, {}),
    ({"prior_mean": "physics", "tied_noise": True, "lengthscale": 0.7},
     {"prior": MapPrior(mean="physics", noise="tied", lengthscale=0.7)},
     {"mean": "physics", "noise": "tied", "lengthscale": 0.7}, {}),
    ({"priors": None, "hyper_posterior": "map"}, {"prior": MapPrior(hyperpriors=None), "hyper_posterior": "map"},
     {"hyperpriors": None}, {}),
    ({"method": "pairs", "tol": 1e-6, "dtype": torch.float32},
     {"engine": Engine(method="pairs", tol=1e-6, dtype=torch.float32)}, {},
     {"method": "pairs", "tol": 1e-6, "dtype": torch.float32}),
]


@pytest.mark.parametrize("flat, new, prior_fields, engine_fields", CASES)
def test_flat_keywords_build_the_model_the_new_spelling_builds(data, flat, new, prior_fields, engine_fields):
    c, f = data
    opts = {"hyper_posterior": "map", **flat}
    with pytest.warns(DeprecationWarning, match="deprecated and will be removed in 0.4") as caught:
        old = irft.InverseRFT(c, f, **opts)
    said = [w for w in caught if issubclass(w.category, DeprecationWarning)]
    assert len(said) == 1 and Path(said[0].filename).resolve() == Path(__file__).resolve()  # the caller's line
    for k in flat:
        if k != "hyper_posterior":
            assert f"{k}=" in str(said[0].message)
    assert ("prior=MapPrior(" in str(said[0].message)) == bool(prior_fields)
    assert ("engine=Engine(" in str(said[0].message)) == bool(engine_fields)
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)  # the new spelling says nothing
        model = irft.InverseRFT(c, f, **{"hyper_posterior": "map", **new})
    expected_prior = {"kernel": "li", "mean": "zero", "hyperpriors": "physical", "noise": "per_axis",
                      "lengthscale": 1.0, **prior_fields}
    expected_engine = {"method": "auto", "tol": 1e-7, "dtype": torch.float64,
                       "max_harmonics": None, **engine_fields}
    for m in (old, model):
        assert {k: getattr(m.prior, k) for k in expected_prior} == expected_prior
        assert {k: getattr(m.engine, k) for k in expected_engine} == expected_engine
    for m in (old, model):  # what the options did to the model itself, read from its machinery
        assert (m.hypers.li is not None) == (expected_prior["kernel"] != "rbf")
        assert (m.hypers.li is not None and m.hypers.li.generic) == (expected_prior["kernel"] == "li+generic")
        assert m.hypers.tied == (expected_prior["noise"] == "tied")
        assert m.prior_mean_kind == expected_prior["mean"] and m.init_lengthscale == expected_prior["lengthscale"]
        assert m.dtype == expected_engine["dtype"] and m.tol == expected_engine["tol"]
        assert m.priors == expected_prior["hyperpriors"]
    assert old.method == model.method
    torch.testing.assert_close(old.loss(), model.loss(), rtol=0, atol=0)


def test_flat_and_new_fits_predict_the_same(data):
    c, f = data
    old = _quiet(c, f, li_basis=False, method="pairs", hyper_posterior="map")
    new = irft.InverseRFT(c, f, prior=MapPrior(kernel="rbf"), engine="pairs", hyper_posterior="map")
    for m in (old, new):
        torch.manual_seed(0)
        m.fit(n_iter=20, progress=False)
    b = torch.linspace(-1.4, 1.4, 7)
    p, q = old.stress_map(b, b.flip(0)), new.stress_map(b, b.flip(0))
    torch.testing.assert_close(p.mean, q.mean, rtol=0, atol=0)
    torch.testing.assert_close(p.variance, q.variance, rtol=0, atol=0)


def test_surface_choice():
    c = irft.rft.contacts(irft.rft.CToe(0.02, 0.008), irft.rft.rectangle_path())[::6]
    f = irft.rft.forces(irft.rft.FourierStressMap.generic(), c)
    assert c.depth is not None
    g = torch.arange(len(c)) % 2
    old = _quiet(c, f, surface_groups=g)
    new = irft.InverseRFT(c, f, surface=g)
    assert old.surface is not None and new.surface is not None and new.surface.grouped
    torch.testing.assert_close(old.surface.groups, new.surface.groups)
    torch.testing.assert_close(old.loss(), new.loss(), rtol=0, atol=0)
    one = irft.InverseRFT(c, f, surface=True)
    assert one.surface is not None and not one.surface.grouped and one.hyper_method == "map"  # its own Laplace std
    assert irft.InverseRFT(c, f, surface=False).surface is None


def test_solver_goes_without_a_replacement(data):
    """``solver`` won nowhere measured: deprecated with no new spelling, still honoured until it goes."""
    c, f = data
    with pytest.warns(DeprecationWarning, match=r"InverseRFT\(solver=\.\.\.\): .* solver= has no replacement"):
        m = irft.InverseRFT(c, f, solver="gpytorch", engine="observations", hyper_posterior="map")
    assert m.solver == "gpytorch" and not hasattr(m.engine, "solver")
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        again = irft.InverseRFT(c, f, **grouped({**m._options(), "method": "observations"}))
    assert again.solver == "gpytorch"
    torch.testing.assert_close(m.loss(), irft.InverseRFT(c, f, engine="observations", hyper_posterior="map").loss())


def test_refusals_name_the_argument(data):
    c, f = data
    with pytest.raises(TypeError, match="pass prior= or the deprecated li_basis="):
        irft.InverseRFT(c, f, prior=MapPrior(), li_basis=True)
    with pytest.raises(TypeError, match="pass engine= or the deprecated method="):
        irft.InverseRFT(c, f, engine="pairs", method="pairs")
    with pytest.raises(TypeError, match="unexpected keyword argument 'li_bases'"):
        irft.InverseRFT(c, f, li_bases=True)
    with pytest.raises(TypeError, match="prior=.*must be a MapPrior"):
        irft.InverseRFT(c, f, prior="li")
    with pytest.raises(TypeError, match="engine=.*must be an Engine"):
        irft.InverseRFT(c, f, engine=3)
    with pytest.raises(ValueError, match="kernel"):
        MapPrior(kernel="matern")
    with pytest.raises(ValueError, match="hyperpriors must be"):
        MapPrior(hyperpriors="flat")
    with pytest.raises(ValueError, match="noise"):
        MapPrior(noise="shared")
    with pytest.raises(ValueError, match="method must be"):
        irft.InverseRFT(c, f, engine="grid-search")
    with pytest.raises(ValueError, match="max_harmonics"):
        irft.InverseRFT(c, f, engine=Engine(max_harmonics=8))


def test_a_saved_model_keeps_its_choices(data, tmp_path):
    """A model file stores the options by their former flat names; loading translates them without a warning and
    gives the same model: choices, machinery and loss (surface groups, the deprecated solver, "auto")."""
    c = irft.rft.contacts(irft.rft.CToe(0.02, 0.008), irft.rft.rectangle_path())[::6]
    f = irft.rft.forces(irft.rft.FourierStressMap.generic(), c)
    g = torch.arange(len(c)) % 2
    m = irft.InverseRFT(c, f, prior=MapPrior(kernel="li+generic", mean="physics", lengthscale=0.8), surface=g)
    m.save(tmp_path / "m.pt")
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        back = irft.InverseRFT.load(tmp_path / "m.pt")
    assert back.prior == MapPrior(kernel="li+generic", mean="physics", hyperpriors="physical", lengthscale=0.8)
    assert back.engine.method == "auto" and back.auto
    assert back.hypers.li.generic and back.prior_mean_kind == "physics" and back.init_lengthscale == 0.8
    torch.testing.assert_close(back.surface.groups, g)
    torch.testing.assert_close(back.loss(), m.loss())
    with pytest.warns(DeprecationWarning):
        s = irft.InverseRFT(c, f, solver="gpytorch", engine="observations", hyper_posterior="map")
    s.save(tmp_path / "s.pt")
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        again = irft.InverseRFT.load(tmp_path / "s.pt")
    assert again.solver == "gpytorch" and again.engine.method == "observations" and not again.auto


def test_defaults_that_follow_the_choices(data):
    """hyper_posterior's default by hand: "laplace", but "map" without hyperparameter priors (an improper
    posterior) or with a learned surface (its own Laplace std); the same through the flat keywords."""
    c = irft.rft.contacts(irft.rft.CToe(0.02, 0.008), irft.rft.rectangle_path())[::6]
    f = irft.rft.forces(irft.rft.FourierStressMap.generic(), c)
    assert irft.InverseRFT(c, f).hyper_method == "laplace"
    assert irft.InverseRFT(c, f, prior=MapPrior(hyperpriors=None)).hyper_method == "map"
    assert irft.InverseRFT(c, f, surface=True).hyper_method == "map"
    assert _quiet(c, f, priors=None).hyper_method == "map"
    assert _quiet(c, f, surface_offset=True).hyper_method == "map"
    assert _quiet(c, f, surface_offset=False).surface is None
    assert _quiet(c, f, surface_offset=False).hyper_method == "laplace"


def test_one_warning_per_call_with_the_values_given(data):
    c, f = data
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        irft.InverseRFT(c, f, li_basis=True, generic_shape=True, tied_noise=False, method="pairs", tol=1e-6,
                        solver="cholesky", surface_offset=False, hyper_posterior="map")
    said = [str(w.message) for w in caught if issubclass(w.category, DeprecationWarning)]
    assert len(said) == 1, said
    assert "prior=MapPrior(kernel='li+generic', noise='per_axis')" in said[0]
    assert "engine=Engine(method='pairs', tol=1e-06)" in said[0]
    assert "surface=None (the default)" in said[0] and "solver= has no replacement" in said[0]


def test_3d_choices():
    from irft_torch.gp.inverse3d import InverseRFT3D

    from .test_inverse3d import turning_toe

    c, f = turning_toe()
    with pytest.warns(DeprecationWarning, match=r"InverseRFT3D\(li_basis=\.\.\., prior_mean=\.\.\., method=\.\.\."):
        old = InverseRFT3D(c, f, li_basis=True, prior_mean="zero", method="pairs")
    new = InverseRFT3D(c, f, prior=MapPrior(kernel="li", mean="zero"), engine="pairs")
    assert old.prior == new.prior == MapPrior(kernel="li", mean="zero")
    assert new.hypers.li is not None and new.mean_scales is None and new.method == "pairs"
    default = irft.InverseRFT(c, f)  # the 3-D defaults filled in
    assert default.prior == MapPrior(kernel="rbf", mean="physics") and default.hypers.li is None
    assert default.mean_scales is not None and default.engine == Engine()
    torch.testing.assert_close(old.loss(), new.loss(), rtol=0, atol=0)
    for bad, what in ((MapPrior(kernel="li+generic"), "planar only"), (MapPrior(noise="tied"), "planar only")):
        with pytest.raises(ValueError, match=what):
            InverseRFT3D(c, f, prior=bad)
    with pytest.raises(TypeError, match="unexpected keyword argument 'solver'"):
        InverseRFT3D(c, f, solver="gpytorch")
    with pytest.raises(TypeError, match="unexpected keyword argument 'tied_noise'"):
        InverseRFT3D(c, f, tied_noise=True)


def _flat_calls(tree: ast.AST) -> list:
    bad = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            name = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else None
            if name in ("InverseRFT", "InverseRFT3D") and any(k.arg in FLAT for k in node.keywords):
                bad.append(node.lineno)
            splats = [k.value for k in node.keywords if k.arg is None and isinstance(k.value, ast.Dict)]
            if name in ("InverseRFT", "InverseRFT3D") and any(isinstance(key, ast.Constant) and key.value in FLAT
                                                              for d in splats for key in d.keys):
                bad.append(node.lineno)
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and "InverseRFT(" in node.value:
            try:  # a script held in a string (run in a subprocess)
                bad += [f"string at {node.lineno}: {n}" for n in _flat_calls(ast.parse(node.value))]
            except SyntaxError:
                pass
    return bad


def test_the_projects_own_code_uses_the_new_spelling():
    """The library, its experiments and notebooks call the front door with the named choices only (a flat
    keyword there would warn every user who runs them)."""
    found = {}
    for folder in ("irft_torch", "experiments"):
        for p in (ROOT / folder).rglob("*.py"):
            lines = _flat_calls(ast.parse(p.read_text()))
            if lines:
                found[str(p.relative_to(ROOT))] = lines
    for p in (ROOT / "notebooks").glob("*.ipynb"):
        for i, cell in enumerate(json.loads(p.read_text())["cells"]):
            if cell["cell_type"] == "code":
                code = "".join(x for x in cell["source"] if not x.lstrip().startswith(("%", "!")))
                lines = _flat_calls(ast.parse(code))
                if lines:
                    found[f"{p.name} cell {i}"] = lines
    assert not found, found
