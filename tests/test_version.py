"""``irft_torch.__version__``: the installed metadata when it is of this copy, else this source tree's
pyproject.toml (checked against hand-written files and stand-in distributions)."""

import pathlib
from importlib import metadata

import pytest

import irft_torch
from irft_torch import _version as V

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_the_package_reports_the_version_pyproject_declares():
    text = (ROOT / "pyproject.toml").read_text()
    declared = next(line.split('"')[1] for line in text.splitlines() if line.startswith("version = "))
    assert irft_torch.__version__ == declared


def test_version_from_pyproject_reads_only_the_project_table(tmp_path):
    p = tmp_path / "pyproject.toml"
    p.write_text('[build-system]\nversion = "9.9"\n\n[project]\nname = "x"\nversion = "1.2.3"\n\n'
                 '[tool.other]\nversion = "7"\n')
    assert V.version_from_pyproject(p) == "1.2.3"
    p.write_text('[project]\nname = "x"\n\n[tool.other]\nversion = "7"\n')
    assert V.version_from_pyproject(p) is None
    assert V.version_from_pyproject(tmp_path / "missing.toml") is None


class _Dist:
    def __init__(self, version, direct_url=None):
        self.version, self._direct_url = version, direct_url

    def read_text(self, name):
        return self._direct_url if name == "direct_url.json" else None


@pytest.mark.parametrize("case, expected", [
    ("regular install", "5.0"),
    ("editable install of this tree", "5.0"),
    ("editable install of another tree", "1.2.3"),
    ("not installed", "1.2.3"),
])
def test_metadata_is_used_only_when_it_is_of_this_copy(case, expected, tmp_path, monkeypatch):
    pkg = tmp_path / "tree" / "irft_torch"
    pkg.mkdir(parents=True)
    (tmp_path / "tree" / "pyproject.toml").write_text('[project]\nname = "irft-torch"\nversion = "1.2.3"\n')
    url = {"editable install of this tree": (tmp_path / "tree").as_uri(),
           "editable install of another tree": (tmp_path / "elsewhere").as_uri()}.get(case)
    direct = None if url is None else f'{{"dir_info": {{"editable": true}}, "url": "{url}"}}'

    def distribution(name):
        assert name == "irft-torch"
        if case == "not installed":
            raise metadata.PackageNotFoundError(name)
        return _Dist("5.0", direct)

    monkeypatch.setattr(V.metadata, "distribution", distribution)
    assert V.package_version(pkg) == expected
    (tmp_path / "tree" / "pyproject.toml").unlink()
    if expected == "1.2.3":  # neither metadata of this copy nor a pyproject.toml: said so, not guessed
        assert V.package_version(pkg) == "0+unknown"
