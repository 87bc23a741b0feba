"""What a log's timestamps say about the logger's clock, read in file order: a clock that restarts
(two recordings appended, each with its own relative times), a clock stepped back or ahead while
recording (an NTP adjustment; relative to absolute time), or a long jump between two recordings.

Sorting such a log by time interleaves the two sides of the break (a restart puts the second
recording's samples between the first's; a step back of 2 s merges 2 s of the recording with
itself) and a jump of a day becomes a day of samples. The motors' encoder positions tell the two
kinds of break apart: across a clock *step* the positions continue (the leg did not move between
two frames); across a new *recording* they jump (the leg is elsewhere), or the clock goes back to
before the recording began. A step is undone (the frames after it re-timed to follow on); a new
recording becomes a segment of its own (``read_log`` returns them in ``LogData.segments``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["ClockBreaks", "clock_breaks", "BACK_TOLERANCE", "JUMP_TOLERANCE"]

BACK_TOLERANCE = 0.1  # s: frames may arrive out of order by less (F14: sorted, reported)
JUMP_TOLERANCE = 1.0  # s: a longer silence is a clock jump (motors where they were: undone) or a new recording
_SUSTAINED = 8  # frames after a step back whose series must all go back (one late frame is disorder)
_ABSOLUTE = 1e8  # s: timestamps above this are seconds since the epoch (absolute), below relative


@dataclass
class ClockBreaks:
    """Per record (file order): the time offset that undoes the clock steps before it (s), and the
    recording (segment) it belongs to; ``notes``: one line per break saying what was found and done."""

    offset: np.ndarray
    segment: np.ndarray
    notes: list = field(default_factory=list)

    @property
    def n_segments(self) -> int:
        return int(self.segment[-1]) + 1 if len(self.segment) else 1


def _continuous(positions: dict, seg_start: int, i: int) -> bool | None:
    """Whether every motor's encoder position continues across record ``i`` (None: no motor has
    positions on both sides within the segment). Continuous: the jump between the last position
    before and the first after is within 5x the largest step among 20 on either side (+1e-4 turn)."""
    verdicts = []
    for idx, pos in positions.values():
        k = int(np.searchsorted(idx, i))
        k0 = int(np.searchsorted(idx, seg_start))
        before, after = pos[max(k0, k - 20):k], pos[k:k + 20]
        if len(before) == 0 or len(after) == 0:
            continue
        steps = np.concatenate([np.abs(np.diff(before)), np.abs(np.diff(after)), [0.0]])
        verdicts.append(abs(after[0] - before[-1]) <= 5 * steps.max() + 1e-4)
    return None if not verdicts else all(verdicts)


def _when(t: float) -> str:
    return f"{t:.3f} s" + (" (absolute)" if abs(t) > _ABSOLUTE else "")


def _previous_same(ids: np.ndarray) -> np.ndarray:
    """(n,) the index of the previous record with the same id (-1 for the first of its id)."""
    prev = np.full(len(ids), -1, dtype=np.int64)
    last: dict = {}
    for k, i in enumerate(ids.tolist()):
        prev[k] = last.get(i, -1)
        last[i] = k
    return prev


def _follow_on(t: np.ndarray, offset: np.ndarray, prev: np.ndarray, seg_start: int, i: int, fallback: float,
               look: int = 64) -> float:
    """The shift that makes each series continue across a clock step at record ``i``: for the records
    after it (up to ``look``) whose series was heard before it, the shift that puts the record one of
    its series' own sampling intervals after its predecessor; their median (a step shifts every series
    alike). A break inside a burst of frames of one instant keeps that instant together this way,
    where one shift for all (the frame spacing) would move half the burst by a sample."""
    shifts = []
    for j in range(i, min(len(t), i + look)):
        p = int(prev[j])
        if p < seg_start or p >= i:
            continue
        steps: list[float] = []
        q = p
        while len(steps) < 10 and prev[q] >= seg_start:
            steps.append((t[q] + offset[q]) - (t[prev[q]] + offset[prev[q]]))
            q = int(prev[q])
        if steps:
            shifts.append(t[p] + offset[p] + float(np.median(steps)) - t[j])
    return float(np.median(shifts)) if shifts else float(fallback)


def clock_breaks(times: np.ndarray, positions: dict, ids=None, frame_numbers=None) -> ClockBreaks:
    """Find and classify the clock breaks of a log.

    Args:
        times: (n,) every record's timestamp in file order, s.
        positions: node -> (record indices (k,) increasing, encoder positions (k,) turns) in file order.
        ids: (n,) each record's frame id (the same for the frames of one series); default all different.
        frame_numbers: (n,) each record's frame number in the file (1-based), for the notes.
    Returns:
        ClockBreaks: ``times + offset`` is the re-timed clock; ``segment`` numbers the recordings.

    A break is a step back by more than ``BACK_TOLERANCE`` that every series takes (the next frames
    are earlier than their own series' frames before it: one late frame, or a file written series
    by series, is disorder, sorted), or a jump ahead by more than ``JUMP_TOLERANCE``. Where the
    motors' positions continue across it (to within a few of their own steps), it is a clock step,
    undone by re-timing the frames after it to follow on; where they jump (or no position tells),
    another recording begins (a segment). A log that stopped for more than a second while the leg
    moved on is read as two recordings: runs are lined up by the toe's path, which has a hole there
    (shorter gaps are masked when resampling).
    """
    t = np.asarray(times, dtype=np.float64)
    n = len(t)
    offset, segment = np.zeros(n), np.zeros(n, dtype=np.int64)
    notes: list[str] = []
    if n < 2:
        return ClockBreaks(offset, segment, notes)
    frame = (np.arange(n) + 1) if frame_numbers is None else np.asarray(frame_numbers)
    prev = _previous_same(np.arange(n) if ids is None else np.asarray(ids))
    d = np.diff(t)
    pos_steps = d[d > 0]
    spacing = float(np.median(pos_steps)) if len(pos_steps) else 0.0
    # candidates from the raw steps (a clock step shifts every later frame alike: their spacing stays)
    cand = np.nonzero((d < -BACK_TOLERANCE) | (d > JUMP_TOLERANCE))[0] + 1
    shift, seg, seg_start = 0.0, 0, 0
    front = float(t[0])  # the latest time so far (re-timed)
    done = 0  # records before this one have their offset and segment
    for i in cand.tolist():
        offset[done:i], segment[done:i] = shift, seg
        front = max(front, float(t[done:i].max()) + shift)
        done = i
        ti = float(t[i]) + shift
        if ti < front - BACK_TOLERANCE:
            j = np.arange(i, min(n, i + _SUSTAINED))
            p = prev[j]
            mine = (p >= seg_start) & (p < i)  # frames whose series was heard before the step, in this recording
            back = t[j[mine]] + shift < t[p[mine]] + offset[p[mine]] - BACK_TOLERANCE / 2
            if not mine.any() or not back.all():
                continue  # a late frame, or a file written series by series: the clock did not move (sorted later)
            cont = _continuous(positions, seg_start, i)
            if not cont:
                why = "and the motors are elsewhere after it" if cont is False else "and no motor position tells"
                notes.append(f"the clock restarts at frame {frame[i]}: the time goes back from {_when(front)} to "
                             f"{_when(ti)} ({why}): another recording appended to this one; read as a recording "
                             "of its own")
                seg, seg_start, front = seg + 1, i, ti
                continue
            new_shift = _follow_on(t, offset, prev, seg_start, i, front + spacing - t[i])
            notes.append(f"the clock steps back {front - ti:.3f} s at frame {frame[i]} (t = {_when(front)}) while the "
                         f"motors' positions continue: the clock was set, not a new recording (an NTP step?); "
                         f"the {n - i} frame(s) after it are re-timed to follow on")
            shift = new_shift
        elif ti > front + JUMP_TOLERANCE:
            gap = ti - front
            cont = _continuous(positions, seg_start, i)
            kind = " (from relative to absolute time)" if abs(front) < _ABSOLUTE <= abs(ti) else ""
            if cont:
                notes.append(f"the clock jumps {gap:.4g} s ahead at frame {frame[i]}{kind} while the motors' positions "
                             f"continue: the clock was set, not a pause; the {n - i} frame(s) after it are re-timed "
                             "to follow on")
                shift = _follow_on(t, offset, prev, seg_start, i, front + spacing - t[i])
            else:  # the leg moved more than a frame allows: the log was not running, this is another recording
                notes.append(f"the clock jumps {gap:.4g} s ahead at frame {frame[i]}{kind} and the motors are "
                             "elsewhere after it: another recording appended to this one; read as a recording of "
                             "its own")
                seg, seg_start, front = seg + 1, i, ti
    offset[done:], segment[done:] = shift, seg
    return ClockBreaks(offset, segment, notes)
