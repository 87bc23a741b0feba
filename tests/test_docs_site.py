"""The documentation site builds with warnings as errors (``mkdocs build --strict``, mkdocs.yml) and
documents the front door, the physics, the backends, design/ and hardware/ from their docstrings,
with the notebooks as guides (rendered as stored: tests/test_notebooks.py executes them)."""

import importlib.util
import os
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
NEEDED = ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers", "mkdocs_jupyter")  # the dev extra's
MISSING = [m for m in NEEDED if importlib.util.find_spec(m) is None]


@pytest.mark.skipif(bool(MISSING), reason=f"the dev extra's site tools are not installed: {MISSING} "
                                          '(pip install -e ".[dev]")')
def test_site_builds_strict_and_documents_the_api(tmp_path):
    site = tmp_path / "site"
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)], cwd=ROOT,
                       capture_output=True, text=True, env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert r.returncode == 0, r.stderr[-4000:]
    page = (site / "api" / "inverse_rft" / "index.html").read_text()
    for name in ("fit", "stress_map", "predict_forces", "sample_maps", "add_data", "cross_validate", "save", "load",
                 "fit_hyper_posterior", "surface_offset"):
        assert f'id="irft_torch.gp.model.InverseRFT.{name}"' in page, name
    assert "(..., T, 2) in N" in page  # shapes and units come through from the docstrings
    expected = {"rft": "irft_torch.rft.contacts.Contacts", "backends": "irft_torch.gp.backends.SpectralBackend",
                "design": "irft_torch.design.scoring.ProbeScorer",
                "hardware": "irft_torch.hardware.five_bar.FiveBarLeg", "data": "irft_torch.data.dataset.Dataset"}
    rft = (site / "api" / "rft" / "index.html").read_text()  # the 3-D contacts and forces
    assert 'id="irft_torch.rft.contacts3d.Contacts3D"' in rft and 'id="irft_torch.rft.forces3d.forces_3d"' in rft
    for api, ident in expected.items():
        assert f'id="{ident}"' in (site / "api" / api / "index.html").read_text(), (api, ident)
    for nb in sorted((ROOT / "notebooks").glob("*.ipynb")):
        assert (site / "notebooks" / nb.stem / "index.html").is_file(), nb.name
