"""The import paths of 0.2 keep working for one release: each warns once, at import, with a
DeprecationWarning on the importing line that names the new home, and gives the same objects."""

import importlib
import subprocess
import sys

import pytest

MOVED = {  # old module -> (new module, a name each must forward)
    "irft_torch.dem_data": ("irft_torch.data.dem", "read_runs"),
    "irft_torch.wheel_data": ("irft_torch.data.wheel", "read_wheel_runs"),
    "irft_torch.reproduce": ("irft_torch.studies.reproduce", "StudySettings"),
    "irft_torch.study_report": ("irft_torch.studies.report", "write_study"),
    "irft_torch.workers": ("irft_torch.studies.workers", "worker_context"),
}


@pytest.mark.parametrize("old", sorted(MOVED))
def test_an_old_path_warns_on_the_importing_line_and_forwards(old, monkeypatch):
    new, name = MOVED[old]
    monkeypatch.delitem(sys.modules, old, raising=False)  # imported afresh: the warning is at import
    with pytest.warns(DeprecationWarning, match=f"{old} moved to {new}"):
        shim = importlib.import_module(old)
    assert getattr(shim, name) is getattr(importlib.import_module(new), name)
    assert name in dir(shim)
    with pytest.raises(AttributeError, match="no_such_name"):
        shim.no_such_name  # noqa: B018


def test_the_old_study_entry_point_is_the_new_one():
    from irft_torch.studies.paper_study import run_study

    with pytest.warns(DeprecationWarning):
        sys.modules.pop("irft_torch.reproduce", None)
        from irft_torch.reproduce import run_study as old
    assert old is run_study


def test_python_shows_the_warning_where_a_script_imports_an_old_path(tmp_path):
    """Attributed to the script's own line (not to importlib), so Python's default filters show it."""
    script = tmp_path / "uses_old_path.py"
    script.write_text("from irft_torch import dem_data\n")
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert f"{script}:1: DeprecationWarning: irft_torch.dem_data moved to irft_torch.data.dem" in r.stderr
