"""hardware.leg_options: a wrong node order, motor direction or gear ratio named by the options under
which the log's toe path is one a leg in sand runs (was: each blamed on --hip-height and --l1/--l2)."""

import pytest

from .fault_logs import ingest


@pytest.mark.parametrize("wrong, hint", [
    (["--directions", "-1", "1"], "--directions 1 1"),
    (["--gear-ratio", "9"], "--gear-ratio 1"),
    (["--gear-ratio", "0.5"], "--gear-ratio 1"),
    (["--nodes", "1", "0"], "--nodes 0 1"),
])
def test_wrong_leg_options_are_named(capsys, tmp_path, sim_logs, wrong, hint):
    rc, out, err, ds = ingest(capsys, tmp_path, sim_logs["trial"], sim_logs["air"], *wrong)
    assert rc == 2 and err.count("\n") == 1
    assert "The toe path is one a leg in sand runs with" in err and hint in err, err
    assert "(the toe reaches 0.051 m below the surface)" in err  # the simulated path's depth, 5 cm + 1 mm of toe


def test_right_options_get_no_hint(capsys, tmp_path, sim_logs):
    """The options are right, the stated hips too high (a toe deeper than the path says): no leg hint, the
    forces' scale names --hip-height."""
    rc, out, err, ds = ingest(capsys, tmp_path, sim_logs["trial"], sim_logs["air"], "--hip-height", "0.3")
    assert rc == 2 and "The toe path" not in err and "--hip-height" in err
