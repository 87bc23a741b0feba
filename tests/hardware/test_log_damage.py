"""10^3 randomly damaged log files (.log, .asc, .blf, .csv; fixed seed): zero tracebacks and zero
silent successes.

Each damaged file must give one of:
- LogReadError (a ValueError) whose ``partial`` holds only frames of the original, in order, and
  every original frame before the damaged byte when the damage is a truncation;
- data with a non-empty ``issues`` list;
- exactly the original content (damage in bytes nothing reads: padding, a comment);
- a ValueError naming two CAN channels (stray bytes inside one frame's channel name: that frame
  is on another bus as far as the file says, and ``read_log`` asks which one to read);
- for line formats (.log, .csv) truncated exactly at a line end: a prefix of the original. Such a
  file is a valid shorter log, undetectable by the reader; ``irft ingest`` catches the short trial
  (its coverage check). The fuzz counts these and checks they are only that.
Anything else (another exception, changed values without a report) fails.
"""

import can
import numpy as np
import pytest

from irft_torch.hardware import LogReadError, encode, read_log

FORMATS = (".log", ".asc", ".blf", ".csv")
GARBAGE = bytes([0, 1, 2, 7, 8, 0x1B, 0x7F, 0x80, 0x9A, 0xC3, 0xFF]) + b"!$%&*;<>?@[]^`{|}~"


def _frames():
    out = []
    for k in range(20):
        t = 1.7e9 + k / 100
        for node in (0, 1):
            out.append(encode("get_encoder_estimates", node, timestamp=t, pos_estimate=0.01 * k + node,
                              vel_estimate=0.5))
        for node in (0, 1):
            out.append(encode("get_iq", node, timestamp=t + 0.002, iq_setpoint=0.1 * k, iq_measured=-0.2 * k - node))
    return out


def _write(path, frames):
    if path.suffix == ".blf":
        writer = can.BLFWriter(str(path), max_container_size=400)  # several containers
    else:
        writer = can.Logger(str(path))
    for m in frames:
        writer.on_message_received(m)
    writer.stop()


def content(data):
    """Every sample as (node, group, time, values), in order."""
    return [(n, g, t, tuple(v)) for n, m in sorted(data.motors.items()) for g in sorted(m.times)
            for t, v in zip(m.times[g], m.values[g])]


def damage(raw: bytes, rng, binary: bool):
    """Truncation anywhere; bytes overwritten or inserted (text: bytes that belong to no token of the
    format: control, non-ASCII, stray punctuation); deleted spans (binary only: deleting characters
    of a text line can leave a valid line with other values, which no checksum-free text format can
    tell apart: see docs/faults.md)."""
    kinds, p = (["truncate", "overwrite", "delete", "insert"], [0.4, 0.3, 0.15, 0.15]) if binary else \
        (["truncate", "overwrite", "insert"], [0.4, 0.4, 0.2])
    kind = rng.choice(kinds, p=p)
    n = len(raw)
    if kind == "truncate":
        cut = int(rng.integers(0, n))
        return raw[:cut], kind, cut
    pos = int(rng.integers(0, n))
    k = int(rng.integers(1, 9))
    junk = (rng.integers(0, 256, k, dtype=np.uint8).tobytes() if binary
            else bytes(rng.choice(list(GARBAGE), k)))
    if kind == "overwrite":
        return raw[:pos] + junk + raw[pos + k:], kind, pos
    if kind == "delete":
        return raw[:pos] + raw[pos + k:], kind, pos
    return raw[:pos] + junk + raw[pos:], kind, pos


def test_thousand_damaged_logs(tmp_path):
    rng = np.random.default_rng(1122)
    frames = _frames()
    originals = {}
    for suffix in FORMATS:
        p = tmp_path / f"orig{suffix}"
        _write(p, frames)
        originals[suffix] = (p.read_bytes(), content(read_log(p)))
        assert read_log(p).issues == []
    tally = {k: 0 for k in ("error", "channel", "reported", "identical", "line-end truncation")}
    for i in range(1000):
        suffix = FORMATS[i % 4]
        raw, want = originals[suffix]
        bad, kind, pos = damage(raw, rng, binary=suffix == ".blf")
        if bad == raw:
            continue
        path = tmp_path / f"d{suffix}"
        path.write_bytes(bad)
        try:
            data = read_log(path)
        except LogReadError as e:
            got = content(e.partial)
            assert str(e) and "\n" not in str(e)
            # the partial data never holds anything the original did not
            assert set(got) <= set(want), (i, suffix, kind, pos, str(e))
            tally["error"] += 1
            continue
        except ValueError as e:  # stray bytes inside a channel name: the frames now name two channels
            assert "sends on 2 CAN channels" in str(e) and "\n" not in str(e), (i, suffix, kind, pos, str(e))
            tally["channel"] += 1
            continue
        got = content(data)
        if data.issues:
            tally["reported"] += 1
        elif got == want:
            tally["identical"] += 1
        else:
            line_end_cut = kind == "truncate" and suffix in (".log", ".csv") and bad.endswith(b"\n")
            by_time = sorted(want, key=lambda r: (r[2], r[0], r[1]))
            assert line_end_cut and sorted(got, key=lambda r: (r[2], r[0], r[1])) == by_time[: len(got)], \
                f"silent success: damage {i} ({kind} at byte {pos} of {suffix}) changed the data without a report"
            tally["line-end truncation"] += 1
    print(tally)
    assert tally["error"] > 600 and tally["line-end truncation"] < 60, tally


@pytest.mark.parametrize("suffix", FORMATS)
def test_truncation_keeps_every_frame_before_the_cut(tmp_path, suffix):
    """Cut each format in the middle: the error says so and the partial data holds every sample the
    file completely held before the cut."""
    frames = _frames()
    p = tmp_path / f"o{suffix}"
    _write(p, frames)
    raw = p.read_bytes()
    want = content(read_log(p))
    cut = len(raw) // 2 + 3  # not at a line end
    q = tmp_path / f"t{suffix}"
    q.write_bytes(raw[:cut])
    with pytest.raises(LogReadError, match="truncated|damaged") as e:
        read_log(q)
    got = content(e.value.partial)
    assert set(got) <= set(want)
    # at least the frames whose bytes lie wholly before the cut: for text, the complete lines
    if suffix != ".blf":
        n_lines = raw[:cut].count(b"\n")
        header = {".log": 0, ".asc": 5, ".csv": 1}[suffix]
        assert len(got) == n_lines - header, (len(got), n_lines)  # one sample per complete frame line
    else:
        assert len(got) >= 30  # BLF containers before the cut (400-byte containers of ~15 frames)
