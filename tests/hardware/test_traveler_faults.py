"""Truncated and damaged Traveler controller logs: an error naming the line, with the rows before
it kept in ``partial``."""

import numpy as np
import pytest

from irft_torch.hardware.traveler import TravelerLogError, read_traveler_log

COLUMNS = ["time", "toeforce_x", "toeforce_y", "toe_position_x", "toe_position_y", "position", "position1",
           "torque", "torque1"]


def _write(path, n=20, end="\r\n"):
    rows = [",".join(f"{k * 0.01 + c * 0.123456:.6f}" for c in range(len(COLUMNS))) for k in range(n)]
    path.write_text("extra,ground_height\r\n" + "0,25,12\r\n" + ",".join(COLUMNS) + "\r\n" + "\r\n".join(rows) + end,
                    newline="")
    return rows


def test_complete_log_reads(tmp_path):
    _write(tmp_path / "t.csv")
    log = read_traveler_log(tmp_path / "t.csv")
    assert len(log) == 20 and log.time[-1] == pytest.approx(0.19) and log.ground_height == pytest.approx(0.12)


@pytest.mark.parametrize("cut_back", [3, 12])  # inside the last number / inside the last row
def test_truncated_log_keeps_the_rows_before_the_cut(tmp_path, cut_back):
    _write(tmp_path / "t.csv")
    raw = (tmp_path / "t.csv").read_bytes()
    (tmp_path / "cut.csv").write_bytes(raw[: len(raw) - 2 - cut_back])
    with pytest.raises(TravelerLogError, match=r"cut.csv: line 23: .*kept the 19 row\(s\) before it") as e:
        read_traveler_log(tmp_path / "cut.csv")
    assert len(e.value.partial) == 19
    np.testing.assert_array_equal(e.value.partial.data, read_traveler_log(tmp_path / "t.csv").data[:19])


def test_damaged_rows_are_named(tmp_path):
    rows = _write(tmp_path / "t.csv")
    text = (tmp_path / "t.csv").read_text()
    (tmp_path / "nan.csv").write_text(text.replace(rows[5], "nan," + rows[5].split(",", 1)[1]))
    with pytest.raises(TravelerLogError, match=r"line 9: non-finite value") as e:
        read_traveler_log(tmp_path / "nan.csv")
    assert len(e.value.partial) == 5
    (tmp_path / "bin.csv").write_bytes(text.encode().replace(rows[0].encode(), b"\xff\xfe" + rows[0][2:].encode()))
    with pytest.raises(TravelerLogError, match=r"line 4: not all numbers") as e:
        read_traveler_log(tmp_path / "bin.csv")
    assert e.value.partial is None
