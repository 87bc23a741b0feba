"""A small run of experiments/validation/fault_fuzz.py (10^3 edited logs per class there, fault_fuzz.md): edited
logs of each class through irft ingest, against the oracle; zero silent-wrong, zero lost, zero refusals
blaming another cause, zero tracebacks."""

from collections import Counter


def test_edited_logs_are_correct_or_refused_for_their_real_cause(sim_logs, fault_fuzz, tmp_path):
    counts = fault_fuzz.run(3, seed=7, folder=tmp_path, base=sim_logs, verbose=True)
    assert set(counts) == set(fault_fuzz.CLASSES)
    total = sum(counts.values(), Counter())
    assert sum(total[f] for f in fault_fuzz.FAILURES) == 0, counts
    assert total["correct"] + total["refused"] == 3 * len(fault_fuzz.CLASSES)
    assert counts["encoder re-zero"]["refused"] == 3 and counts["clock step back"]["correct"] == 3
