"""What a log's buses and series say: several CAN channels with the same node ids, a series that ends
early (a pulled connector), an encoder re-zeroed mid-trial, a resampling rate far from the log's; each
refused with its real cause or handled and said, the datasets checked against the oracle."""

import pytest

from irft_torch.hardware import read_log

from .fault_logs import dump, ingest, shift_position

TOL = 0.05  # N


def _mixed(sim_logs, other_ids=False):
    """The trial on can0 and another leg's trial (looser sand) on can1, merged by time (candump -L any)."""
    extra = []
    for t, _, r in sim_logs["other"]:
        if other_ids:
            ident, rest = r.split("#", 1)
            r = f"{int(ident, 16) + (2 << 5):03X}#{rest}"
        extra.append([t + 1e-5, "can1", r])
    return sorted(sim_logs["trial"] + extra, key=lambda ln: ln[0])


def test_two_buses_with_the_same_node_ids_need_a_channel(capsys, tmp_path, sim_logs):
    """(was: the channel ignored, two legs read as one) refused naming the channels; with --channel the
    leg's own forces (within the oracle of its sand); another leg with other ids needs no channel."""
    mixed = _mixed(sim_logs)
    with pytest.raises(ValueError, match=r"node 0 sends on 2 CAN channels \(can0: \d+ samples, can1: \d+ samples\)"
                                         r".*channel='can0'"):
        read_log(dump(mixed, tmp_path / "m.log"))
    rc, out, err, ds = ingest(capsys, tmp_path, mixed, sim_logs["air"])
    assert rc == 2 and "irft ingest --channel can0" in err and err.count("\n") == 1
    rc, out, err, ds = ingest(capsys, tmp_path, mixed, sim_logs["air"], "--channel", "can0")
    assert rc == 0 and sim_logs["oracle"](ds) < TOL
    assert read_log(tmp_path / "m.log", channel="can1").motors[0].arrays("iq")[1].shape == \
        read_log(dump(sim_logs["other"], tmp_path / "o.log")).motors[0].arrays("iq")[1].shape
    rc, out, err, ds = ingest(capsys, tmp_path, _mixed(sim_logs, other_ids=True), sim_logs["air"])
    assert rc == 0 and sim_logs["oracle"](ds) < TOL
    with pytest.raises(ValueError, match="holds no frames on CAN channel 'can7'; its channels: can0"):
        read_log(dump(sim_logs["trial"], tmp_path / "t.log"), channel="can7")


@pytest.mark.parametrize("node, ident", [(1, "029"), (0, "014")], ids=["node-1-encoder", "node-0-current"])
def test_a_series_that_stops_early_crops_the_run_and_says_so(capsys, tmp_path, sim_logs, node, ident):
    """(was: the trial cropped silently to where every series overlaps) a pulled connector: the samples
    it cuts off are counted (by hand: the time after the cut x the rate), a one-line warning names the
    node, and what is kept matches the oracle."""
    trial = sim_logs["trial"]
    t_end = trial[-1][0]
    cut = trial[0][0] + 0.6 * (t_end - trial[0][0])
    lines = [ln for ln in trial if not (ln[2].startswith(ident + "#") and ln[0] > cut)]
    log = read_log(dump(lines, tmp_path / "cut.log")).resample()
    (reason, count), = ((k, v) for k, v in log.masked.items() if "stops" in k)
    what = "encoder" if ident.endswith("9") else "current"
    assert reason.startswith(f"node {node} {what} stops") and "pulled connector" in reason
    assert abs(count - (t_end - cut) * 100) <= 2
    rc, out, err, ds = ingest(capsys, tmp_path, lines, sim_logs["air"])
    assert rc == 0 and sim_logs["oracle"](ds) < TOL
    warning, = (ln for ln in err.splitlines() if "stops" in ln)
    assert warning.startswith("irft ingest: warning: ") and f"node {node} {what} stops" in warning
    assert float(ds.time[-1] - ds.time[0]) < 0.62 * (t_end - trial[0][0])


@pytest.mark.parametrize("jump", [0.25, -0.04])
def test_an_encoder_re_zeroed_mid_trial_is_named(capsys, tmp_path, sim_logs, jump):
    """(was: blamed on the air run, or on a good second trial) the position jump is named with its size
    (by hand: the shift, give or take one sample's motion, under 0.002 turn here)."""
    trial = sim_logs["trial"]
    cut = trial[len(trial) // 2][0]
    lines = [[t, c, shift_position(r, jump) if r.startswith("009#") and t > cut else r] for t, c, r in trial]
    with pytest.raises(ValueError, match="node 0's encoder jumps by .* re-zeroed mid-recording") as e:
        read_log(dump(lines, tmp_path / "z.log")).resample()
    size = float(str(e.value).split("jumps by ")[1].split()[0])
    assert abs(size - jump) < 2e-3
    rc, out, err, ds = ingest(capsys, tmp_path, [sim_logs["trial"], lines], sim_logs["air"])
    assert rc == 2 and "t1.log: node 0's encoder jumps" in err and "air run" not in err


@pytest.mark.parametrize("rate, word", [(0.2, "below"), (200000, "above")])
def test_a_rate_far_from_the_logs_is_refused(capsys, tmp_path, sim_logs, rate, word):
    """(was: --rate 0.2 on a 100 Hz log wrote a 3-sample dataset; --rate 200000 ran out of memory)"""
    rc, out, err, ds = ingest(capsys, tmp_path, sim_logs["trial"], sim_logs["air"], "--rate", str(rate))
    assert rc == 2 and f"rate {rate:g} Hz is {word} the log's own 100 Hz" in err and "within 10x" in err
    rc, out, err, ds = ingest(capsys, tmp_path, sim_logs["trial"], sim_logs["air"], "--rate", "50")
    assert rc == 0 and sim_logs["oracle"](ds) < TOL


def test_a_filter_window_longer_than_a_tenth_of_the_run_is_refused(capsys, tmp_path, sim_logs):
    """(was: --filter-window longer than the trial flattened the forces, exit 0)"""
    rc, out, err, ds = ingest(capsys, tmp_path, sim_logs["trial"], sim_logs["air"], "--filter-window", "101")
    assert rc == 2 and "argument --filter-window: 101 samples is" in err and "flattens the force" in err
