"""Live on the robot: CAN frames in, an updated terrain estimate out after every stance, every frame
logged.

    bus --Notifier--> intake: every frame to the log (python-can's writers, rotated by size), then
                      into a bounded queue
    worker thread:    frames -> per-motor series on one time base (``resample``) -> q, tau
                      -> F = -J^-T tau (``five_bar``) [- the air run's force] -> the offline moving
                      average, causally (``causal_filter``) -> stance onset and end (``stance``)
                      -> that stance's contacts (``rft.contacts``) and forces -> checked
                      (``rft.force_checks``) -> ``model.add_data`` -> an estimate published: the
                      callback, JSON lines, model snapshots, a progress line

The model is any object with ``add_data(contacts, forces)``, ``predict_forces(contacts,
include_noise=True)``, ``stress_map(beta, gamma)`` and ``save(path)`` (``gp.InverseRFT``; this module
imports no ``gp``: hardware and gp share a floor). Without one, ``start_model(contacts, forces)``
builds it from the first ``warmup`` stances (``irft live`` fits an ``InverseRFT`` with the plug-in
hyperparameters there).

Faults, each with a defined behaviour (docs/real_leg.md, "Live"), never silent:

- a motor that stops sending: after ``stale_after`` s the estimate is marked stale (every estimate and
  status says so) and the stance in progress is dropped; it recovers when both motors speak again;
- frames out of order or repeated: dropped and counted (``resample``); a clock step: undone;
- a stance with no segment in contact at the stated surface, or with forces no granular medium gives
  (``force_faults``: the offline ingest check, per stance): not used, reported with the reason;
- the queue between the bus and the worker falling behind: bounded (``max_queue`` frames); beyond it
  frames still go to the log but not to the estimate, the stances they touch are dropped, reported;
- bus errors: error frames counted and reported; a bus whose ``recv`` fails (bus-off, an unplugged
  adapter) is closed and reopened with ``bus_factory`` (backoff 0.1 s doubling to 2 s), reported.

A crash or Ctrl-C leaves the log readable up to its last write (``stop`` closes it; a text log cut
mid-line is read up to there by ``read_log``) and the last complete snapshot (written atomically).
"""

from __future__ import annotations

import math
import queue
import threading
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import numpy as np
import torch

from ...rft.contacts import Contacts, contacts
from ...rft.force_checks import force_faults
from ...rft.paths import pose_path
from ...rft.stress_maps import FourierStressMap
from ...rft.toes import Toe
from ..bus.odrive_can import FrameError, decode
from ..five_bar import FiveBarLeg, SingularConfigurationWarning
from ..motor import MotorModel
from .causal_filter import CausalMovingAverage
from .estimate import MAP_POINTS, NO_AIR, SCALE_DRAWS, UNNAMED, LiveEstimate
from .intake import CanIntake
from .resample import LiveResampler
from .stance import Stance, StanceDetector

__all__ = ["LiveEstimator", "LiveEstimate", "MAP_POINTS"]


class LiveEstimator:
    """Frames from a CAN bus in, an updated terrain estimate out after every stance.

    Args:
        bus: a python-can bus (any interface), or None with ``bus_factory``.
        leg: the leg's kinematics (as for ingest).
        motors: its two motors (k_t, directions, zero offsets, gear ratios).
        toe: the toe (rft), at a fixed ``heading``.
        hip_height: the motor axes' height above the sand's surface, m.
        model: a fitted model to update (``gp.InverseRFT``; pass ``hyper_posterior="map"`` there: each
            update then costs one rank-T update), or None with ``start_model``.
        start_model: ``start_model(contacts, forces) -> model`` on the first ``warmup`` stances.
        warmup: stances ``start_model`` is given.
        callback: ``callback(LiveEstimate)`` after each stance and status change (in the worker thread:
            a slow callback delays the next update, the queue absorbs it).
        nodes: the controllers' node ids (motor 1, motor 2).
        firmware: ODrive CANSimple layout, "0.5" or "0.6".
        rate: the controllers' message rate, Hz (the time base).
        filter_window: the moving average's window, odd, samples (as ingest's).
        stance: "surface" or "force" (``StanceDetector``).
        force_threshold: N, for ``stance="force"``.
        heading: the toe's fixed heading, rad.
        air: the force measured in air along the stride, ``air(toe) -> (n, 2)`` N from leg-frame toe
            positions (n, 2) m, subtracted before the filter (``hardware.AirBaseline.from_log``: a stored air
            run); NaN rows are masked and counted; None: nothing subtracted.
        out_dir: where the log, ``live.jsonl`` and ``model.pt`` go (None: nothing written).
        log_name: the log's file name; its suffix picks the format (.blf, .asc, .log, .csv).
        max_log_bytes: rotate the log at this size (python-can's ``SizedRotatingLogger``; 0: one file).
        json_stream: a text stream to write the JSON lines to as well (``sys.stdout``).
        snapshot_period: s between model snapshots (and one at the end).
        stale_after: s of silence from a motor before the estimate is marked stale.
        max_queue: frames the queue holds before it drops (from the estimate, never from the log).
        check_medium: refuse stances whose forces no granular medium gives (the ingest check).
        bus_factory: ``bus_factory() -> bus`` to reconnect after a bus error (and to open the first bus
            when ``bus`` is None).
        max_current: |current| above this, A, is an outlier (dropped, counted).
        progress: a terminal progress line (tqdm) on stderr.

    Example:
        >>> est = LiveEstimator(can.Bus("can0", interface="socketcan"), leg, motors, toe, hip_height=0.25,
        ...                     model=InverseRFT.load("prior.pt"), out_dir="walk/", callback=print)
        >>> with est:
        ...     time.sleep(60)                   # walk; est.last is the newest estimate
    """

    def __init__(self, bus: can.BusABC | None, leg: FiveBarLeg, motors: tuple[MotorModel, MotorModel], toe: Toe,
                 hip_height: float, model: Any = None, start_model: Callable | None = None, warmup: int = 3,
                 callback: Callable | None = None, nodes=(0, 1), firmware: str = "0.5", rate: float = 1000.0,
                 filter_window: int = 5, stance: str = "surface", force_threshold: float = 1.0,
                 heading: float = 0.0, air: Callable | None = None, out_dir=None, log_name: str = "frames.blf",
                 max_log_bytes: int = 0, json_stream=None, snapshot_period: float = 10.0,
                 stale_after: float = 0.1, max_queue: int = 200_000, check_medium: bool = True,
                 bus_factory: Callable | None = None, max_current: float | None = 80.0,
                 progress: bool = False) -> None:
        if bus is None and bus_factory is None:
            raise ValueError("bus: give a python-can bus, or bus_factory to open one")
        if model is None and start_model is None:
            raise ValueError("model: give a fitted model to update, or start_model to build one from the first "
                             "stances")
        if int(warmup) != warmup or warmup < 1:
            raise ValueError(f"warmup must be a positive number of stances, got {warmup}")
        if not (math.isfinite(hip_height) and hip_height > 0):
            raise ValueError(f"hip_height must be the motor axes' positive height above the surface in m, got "
                             f"{hip_height}")
        for name, v in (("snapshot_period", snapshot_period), ("stale_after", stale_after)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be positive seconds, got {v}")
        if int(max_queue) != max_queue or max_queue < 100:
            raise ValueError(f"max_queue must be an integer >= 100 (frames), got {max_queue}")
        if int(max_log_bytes) != max_log_bytes or max_log_bytes < 0:
            raise ValueError(f"max_log_bytes must be an integer >= 0 (0: no rotation), got {max_log_bytes}")
        if not math.isfinite(heading):
            raise ValueError(f"heading must be a finite angle in rad, got {heading}")
        self.leg, self.motors, self.toe = leg, tuple(motors), toe
        self.hip_height, self.heading = float(hip_height), float(heading)
        self.model, self.start_model, self.warmup = model, start_model, int(warmup)
        self.callback, self.firmware, self.air = callback, str(firmware), air
        self.stale_after, self.snapshot_period = float(stale_after), float(snapshot_period)
        self.check_medium, self.bus_factory, self.json_stream = check_medium, bus_factory, json_stream
        self.nodes = tuple(int(n) for n in nodes)
        self.resampler = LiveResampler(self.nodes, rate, max_current=max_current)
        self.filter = CausalMovingAverage(filter_window, 2)
        c, s = math.cos(self.heading), math.sin(self.heading)
        lowest = float((toe.centres[:, 0] * s + toe.centres[:, 1] * c).min())  # z of the rotated centres
        self.detector = StanceDetector(stance, lowest=lowest, threshold=force_threshold)
        self.out_dir = None if out_dir is None else Path(out_dir)
        self.log_path: Path | None = None
        self.snapshot_path: Path | None = None
        self._jsonl = None
        logger = None
        if self.out_dir is not None:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            self.log_path = self.out_dir / log_name
            logger = (can.SizedRotatingLogger(str(self.log_path), max_bytes=int(max_log_bytes)) if max_log_bytes
                      else can.Logger(str(self.log_path)))
            self.snapshot_path = self.out_dir / "model.pt"
            self._jsonl = open(self.out_dir / "live.jsonl", "a", encoding="utf-8")  # noqa: SIM115 - closed in stop
        self._logger = logger
        self.intake = CanIntake(logger, int(max_queue))
        self.bus = bus
        self._notifier: can.Notifier | None = None
        self._worker: threading.Thread | None = None
        self._stop = threading.Event()
        self.last: LiveEstimate | None = None
        self.n_stances = self.n_updates = 0
        self.latencies: list[float] = []  # s, end of stance (its closing frames' arrival) to estimate, per update
        self.compute_times: list[float] = []  # s, of the stance's processing alone
        self.unused: dict[str, int] = {}
        self.reconnections = 0
        self.no_air_force = 0  # samples masked: no air-run sample within the baseline's max_distance
        self.error: BaseException | None = None
        self._warm: list[tuple[Contacts, torch.Tensor]] = []
        self._stale = False
        self._source_ended = False  # drain(ended=True): the source stopped on purpose, its silence is no fault
        self._heard: dict[int, float] = {}  # arrival of each node's last frame the worker has processed
        self._heard_t: dict[int, float] = {}  # and its time on the frames' clock, s
        self._dropped_seen = 0
        self._errors_seen = 0
        self._notes_seen = 0
        self._last_snapshot = time.monotonic()
        self._status_at = 0.0
        self._drop_said = -math.inf
        self._bar = None
        if progress:
            from tqdm.auto import tqdm

            self._bar = tqdm(desc="irft live", unit=" stance", dynamic_ncols=True)

    # ---- running -------------------------------------------------------------------------------
    def start(self) -> LiveEstimator:
        """Start listening (the Notifier) and processing (a worker thread)."""
        if self.bus is None:
            self.bus = self.bus_factory()
        self._notifier = can.Notifier(self.bus, [self.intake], timeout=0.05)
        self._stop.clear()
        self._worker = threading.Thread(target=self._run, name="irft-live", daemon=True)
        self._worker.start()
        return self

    def stop(self, timeout: float = 10.0) -> None:
        """Stop listening, process what is queued, close the log, write the last snapshot."""
        if self._notifier is not None:
            self._notifier.stop()
            self._notifier = None
        self._stop.set()
        if self._worker is not None:
            self._worker.join(timeout)
            self._worker = None
        if self._logger is not None:
            self._logger.stop()
            self._logger = None
        if self.model is not None and self.snapshot_path is not None and self.n_updates:
            self._snapshot()
        self._publish(LiveEstimate("end", message=self._end_message()))
        if self._jsonl is not None:
            self._jsonl.close()
            self._jsonl = None
        if self._bar is not None:
            self._bar.close()

    def __enter__(self) -> LiveEstimator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def wait(self, timeout: float | None = None) -> None:
        """Block until ``stop`` (from another thread, or Ctrl-C here), or ``timeout`` s."""
        end = math.inf if timeout is None else time.monotonic() + timeout
        while not self._stop.is_set() and time.monotonic() < end:
            time.sleep(0.05)
        if self.error is not None:
            raise self.error

    def drain(self, timeout: float = 10.0, ended: bool = False) -> None:
        """Wait until the queue is empty, the worker idle and nothing has come from the bus for 0.2 s (tests,
        benchmarks, the end of a simulated walk: the Notifier's thread may lag the sender on a loaded host).

        ended: the source has stopped sending on purpose (a simulated walk or a replay at its end): the silence
        that follows is not a fault and does not mark the estimate stale."""
        self._source_ended = self._source_ended or ended
        end = time.monotonic() + timeout
        heard = -1  # frames received at the last idle look: the Notifier may still be reading the bus behind
        while time.monotonic() < end:
            if self.intake.queue.unfinished_tasks or not self.intake.queue.empty():
                time.sleep(0.01)
            elif self.intake.received != heard:  # idle, but was anything read since the last look?
                heard = self.intake.received
                time.sleep(0.2)
            else:  # idle, and nothing came from the bus for 0.2 s
                break

    @property
    def stale(self) -> bool:
        return self._stale

    # ---- the worker ----------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            while True:
                block = self._take()
                if block:
                    try:
                        self._process(block)
                    finally:
                        for _ in block:
                            self.intake.queue.task_done()
                self._check_health()
                if self._stop.is_set() and self.intake.queue.empty():
                    break
            self._finish_stream()
        except BaseException as e:  # noqa: BLE001 - kept, reported, re-raised by wait()
            self.error = e
            self._publish(LiveEstimate("status", message=f"the live estimator stopped: {type(e).__name__}: {e}"))
            self._stop.set()

    def _take(self, most: int = 4096) -> list:
        q = self.intake.queue
        try:
            first = q.get(timeout=0.02)
        except queue.Empty:
            return []
        block = [first]
        while len(block) < most:
            try:
                block.append(q.get_nowait())
            except queue.Empty:
                break
        return block

    def _process(self, block: list) -> None:
        rs = self.resampler
        for arrival, msg in block:
            if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
                continue
            try:
                frame = decode(msg, self.firmware)
            except FrameError:
                continue
            if frame.node not in self.nodes:
                continue
            t = rs.retime(msg.timestamp, arrival)
            self._heard_from(frame.node, t, arrival)
            group = {"get_encoder_estimates": "encoder", "get_iq": "iq", "heartbeat": "heartbeat"}.get(frame.command)
            if group is None:
                continue
            v = frame.values
            values = ((v["pos_estimate"], v["vel_estimate"]) if group == "encoder" else
                      (v["iq_setpoint"], v["iq_measured"]) if group == "iq" else
                      (float(v["axis_error"] != 0 or any(v.get(k, 0) & 1 for k in
                                                         ("motor_error_flag", "encoder_error_flag",
                                                          "controller_error_flag"))), v["axis_state"]))
            rs.add(frame.node, group, t, values, arrival)
        grid = rs.ready()
        while self._notes_seen < len(rs.notes):
            self._status(rs.notes[self._notes_seen])
            self._notes_seen += 1
        if len(grid) == 0:
            return
        q = torch.stack([self.motors[i].joint_angle(torch.as_tensor(grid.position[:, i])) for i in range(2)], -1)
        tau = torch.stack([self.motors[i].torque(torch.as_tensor(grid.current[:, i])) for i in range(2)], -1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SingularConfigurationWarning)
            toe = self.leg.forward_kinematics(q)
            force, ok = self.leg.ground_force(q, tau, warn=False)
        toe_np, force_np = toe.numpy(), force.numpy()
        valid = grid.valid & ok.numpy() & np.isfinite(toe_np).all(1)
        if self.air is not None:
            force_np = force_np - np.asarray(self.air(toe_np), dtype=float)
            no_air = valid & ~np.isfinite(force_np).all(1)
            if no_air.any():  # the toe is where the air run never was: masked, counted
                self.no_air_force += int(no_air.sum())
            valid &= ~no_air
        for k in range(len(grid)):
            payload = (toe_np[k, 0], toe_np[k, 1] + self.hip_height, grid.arrival[k])
            for s in self.filter.push(grid.time[k], force_np[k], bool(valid[k]), payload):
                self._sample(s)

    def _sample(self, s) -> None:
        x, z, arrival = s.payload
        for stance in self.detector.push(s.time, (x, z), s.value, s.valid, arrival):
            self._stance(stance)

    def _finish_stream(self) -> None:
        """End of the stream: the filter's last samples; a stance still in progress is incomplete (its
        end was never seen) and is not used."""
        for s in self.filter.flush():
            self._sample(s)
        if self.detector.in_stance:
            st = self.detector.reset()
            if st is not None:
                self._unused(st, "incomplete: the stream ended inside it")

    # ---- a stance ------------------------------------------------------------------------------
    def _stance(self, st: Stance) -> None:
        self.n_stances += 1
        t0 = time.monotonic()
        with torch.no_grad():  # the estimate carries no gradients (the model's hyperparameters are fixed here)
            self._stance_update(st)
        self.compute_times.append(time.monotonic() - t0)

    def _stance_update(self, st: Stance) -> None:
        if self.intake.dropped > self._dropped_seen:
            self._dropped_seen = self.intake.dropped
            return self._unused(st, "frames were dropped while it was recorded (the queue fell behind)")
        path = pose_path(torch.as_tensor(st.time), torch.as_tensor(st.toe[:, 0]), torch.as_tensor(st.toe[:, 1]),
                         torch.full((len(st.time),), self.heading, dtype=torch.float64))
        c_all = contacts(self.toe, path)
        c = Contacts(*(v[st.first:st.last] for v in c_all.as_dict().values()))
        f = torch.as_tensor(st.force[st.first:st.last])
        if not bool((c.weight_z != 0).any()):
            depth = -float(st.toe[st.first:st.last, 1].min()) - self.detector.lowest
            return self._unused(st, f"no segment in contact at the stated surface (the lowest segment reaches "
                                    f"{depth:+.4f} m deep): check hip_height")
        if self.check_medium:
            faults = force_faults(c, f)
            if faults:
                return self._unused(st, f"forces implausible for a granular medium: {faults[0].finding}")
        est = LiveEstimate("stance", stance=self.n_stances, t_start=st.start, t_end=st.end, samples=st.n_samples)
        if self.model is None:
            self._warm.append((c, f))
            if len(self._warm) < self.warmup:
                est.message = f"kept for the start model ({len(self._warm)} of {self.warmup} stances)"
                est.used = True  # its forces go into the start model
                return self._publish_stance(est, st, update=False)
            cs, fs = zip(*self._warm)
            joined = Contacts(*(torch.cat(v) for v in zip(*(x.as_dict().values() for x in cs))))
            self.model = self.start_model(joined, torch.cat(fs))
            self._warm = []
            est.message = f"start model built from the first {self.warmup} stances"
            if self.snapshot_path is not None:
                self._snapshot()
        else:
            pred = self.model.predict_forces(c, include_noise=True)
            r = (f - pred.mean).numpy()
            est.residual_rms = np.sqrt((r**2).mean(0)).tolist()
            est.residual_z = float(np.sqrt((r**2 / pred.variance.numpy()).mean()))
            self.model.add_data(c, f)
        est.used = True
        self.n_updates += 1
        self._summarise(est)
        self._publish_stance(est, st)
        if time.monotonic() - self._last_snapshot >= self.snapshot_period:
            self._snapshot()

    def _summarise(self, est: LiveEstimate) -> None:
        b, gam = torch.as_tensor(MAP_POINTS[:, 0]), torch.as_tensor(MAP_POINTS[:, 1])
        post = self.model.stress_map(b, gam)
        mean, std = post.mean.detach().cpu().numpy(), post.variance.detach().clamp_min(0).sqrt().cpu().numpy()
        g = FourierStressMap.generic()(b, gam).numpy()
        w = g**2 / np.maximum(std, 1e-300) ** 2
        a = w / w.sum(0) / g  # (81, 2): the scale is sum_i a_i alpha(point i), per axis
        est.scale = (a * mean).sum(0).tolist()
        # its std from the joint posterior (neighbouring points are correlated: taken as independent, the std was
        # half of this on the simulated walk, and the truth 4 of those stds away)
        if getattr(self.model, "hyper_posterior", None) is None and getattr(self.model, "mean_average", None) is None:
            with torch.no_grad():  # one backend (the plug-in): a^T Sigma a exactly, Sigma (2, 81, 81)
                cov = self.model.backend.posterior(Contacts.points(b, gam), covariance=True).covariance.cpu().numpy()
            est.scale_std = np.sqrt(np.maximum(np.einsum("na,anm,ma->a", a, cov, a), 0)).tolist()
        else:  # a mixture over hyperparameters or means: from maps drawn jointly
            gen = torch.Generator(device=post.mean.device).manual_seed(0)
            draws = self.model.sample_maps(b, gam, n=SCALE_DRAWS, generator=gen).detach().cpu().numpy()
            est.scale_std = (draws * a).sum(1).std(0, ddof=1).tolist()
        est.map_mean, est.map_std = mean, std

    def _unused(self, st: Stance, why: str) -> None:
        key = why.split(":")[0]
        self.unused[key] = self.unused.get(key, 0) + 1
        est = LiveEstimate("stance", stance=self.n_stances, used=False, why_unused=why, t_start=st.start,
                           t_end=st.end, samples=st.n_samples)
        self._publish_stance(est, st)

    def _publish_stance(self, est: LiveEstimate, st: Stance, update: bool = True) -> None:
        est.latency = time.monotonic() - float(st.arrival[-1])
        if est.used and update:
            self.latencies.append(est.latency)
        self._publish(est)

    # ---- health --------------------------------------------------------------------------------
    def _check_health(self) -> None:
        now = time.monotonic()
        if self.intake.queue.empty():  # caught up: a silence now is the motors', not the worker's backlog
            silent = {n: now - t for n, t in self._heard.items()}
            if len(silent) == len(self.nodes) and not self._stale and not self._source_ended:
                node = max(silent, key=lambda n: silent[n])
                if silent[node] > self.stale_after:
                    self._go_stale(node, f"node {node} has sent nothing for {silent[node]:.2f} s")
        if self.intake.dropped > self._dropped_seen:
            if now - self._drop_said > 1.0:  # said at most once a second
                self._drop_said = now
                self._status(f"the queue fell behind: {self.intake.dropped} frame(s) not processed so far (all "
                             f"logged); queue bound {self.intake.queue.maxsize} frames")
            detector_stance = self.detector.reset()
            if detector_stance is not None:
                self.n_stances += 1
                self._unused(detector_stance, "frames were dropped while it was recorded (the queue fell behind)")
            self._dropped_seen = self.intake.dropped
            self.resampler.restart()  # the dropped stretch is not bridged: a new time base from the next frames
            self.filter = CausalMovingAverage(self.filter.window, 2)
        if self.intake.error_frames > self._errors_seen and now - self._status_at > 1.0:
            self._status(f"{self.intake.error_frames - self._errors_seen} CAN error frame(s) (bus errors: wiring, "
                         "termination, bit rate)")
            self._errors_seen = self.intake.error_frames
        if self.intake.error is not None:
            self._reconnect()

    def _go_stale(self, node: int, what: str) -> None:
        """A motor fell silent: the stance in progress is dropped, the time base restarts when both speak."""
        self._stale = True
        dropped = self.detector.reset()
        if dropped is not None:
            self.n_stances += 1
            self._unused(dropped, f"node {node} fell silent during it")
        self.resampler.restart()
        self.filter = CausalMovingAverage(self.filter.window, 2)
        self._status(f"{what}: the estimate is stale (not updated) until it sends again")

    def _heard_from(self, node: int, t: float, arrival: float) -> None:
        """Staleness in the frames' order and on their clock (t, s): a backlog the worker catches up on, or a
        host too busy to take frames for a moment while the bus buffers them, is not a motor's silence."""
        prev = self._heard_t.get(node)
        self._heard[node], self._heard_t[node] = arrival, t
        if prev is not None and t - prev > self.stale_after and not self._stale:
            self._go_stale(node, f"node {node} sent nothing for {t - prev:.2f} s")
        if self._stale and len(self._heard_t) == len(self.nodes) and \
                max(t - u for u in self._heard_t.values()) <= self.stale_after:
            self._stale = False
            self._status("both motors are sending again: the estimate is live")

    def _reconnect(self) -> None:
        exc = self.intake.error
        if self.bus_factory is None:
            raise RuntimeError(f"bus error: {type(exc).__name__}: {exc}; no bus_factory to reconnect with")
        self._status(f"bus error: {type(exc).__name__}: {exc}; reconnecting")
        if self._notifier is not None:
            self._notifier.stop()
        try:
            self.bus.shutdown()
        except Exception:  # noqa: BLE001 - a bus that failed may fail to close; a new one is opened anyway
            pass
        dropped = self.detector.reset()
        if dropped is not None:
            self.n_stances += 1
            self._unused(dropped, "the bus failed during it")
        self.resampler.restart()
        self.filter = CausalMovingAverage(self.filter.window, 2)
        wait = 0.1
        while not self._stop.is_set():
            try:
                self.bus = self.bus_factory()
                break
            except Exception as e:  # noqa: BLE001 - any failure to open: try again
                self._status(f"reconnecting failed: {type(e).__name__}: {e}; next try in {wait:.1f} s")
                time.sleep(wait)
                wait = min(2 * wait, 2.0)
        with self.intake.lock:
            self.intake.error = None
        if not self._stop.is_set():
            self._notifier = can.Notifier(self.bus, [self.intake], timeout=0.05)
            self.reconnections += 1
            self._status(f"reconnected ({self.reconnections} so far)")

    # ---- output --------------------------------------------------------------------------------
    def _status(self, message: str) -> None:
        self._status_at = time.monotonic()
        self._publish(LiveEstimate("status", stance=self.n_stances, message=message))

    def _publish(self, est: LiveEstimate) -> None:
        now = time.monotonic()
        seen = dict(self.intake.last_seen)
        silent = [now - seen[n] for n in self.nodes if n in seen]
        est.stale = self._stale
        est.staleness = max(silent) if silent else math.inf
        est.frames, est.dropped, est.updates = self.intake.received, self.intake.dropped, self.n_updates
        est.counts = {**{k: v for k, v in self.resampler.counts.items() if v},
                      **({"error frames": self.intake.error_frames} if self.intake.error_frames else {}),
                      **({NO_AIR: self.no_air_force} if self.no_air_force else {}),
                      **({UNNAMED: self.intake.unnamed_channel} if self.intake.unnamed_channel else {}),
                      **({"unused stances: " + k: v for k, v in self.unused.items()})}
        if est.event == "stance":
            self.last = est
        line = est.as_json()
        for stream in (self._jsonl, self.json_stream):
            if stream is not None:
                stream.write(line + "\n")
                stream.flush()
        if self._bar is not None:
            if est.event == "stance":
                self._bar.update(1)
                self._bar.set_postfix_str(self._headline(est), refresh=False)
            elif est.message:
                self._bar.write(f"irft live: {est.message}")
        if self.callback is not None:
            self.callback(est)

    @staticmethod
    def _headline(est: LiveEstimate) -> str:
        if est.used and math.isnan(est.scale[0]):
            return f"stance {est.stance}: {est.message}"
        if not est.used:
            return f"stance {est.stance} not used: {est.why_unused}"
        sx, sz = est.scale
        dx, dz = est.scale_std
        return (f"scale x {sx:.3f}±{dx:.3f} z {sz:.3f}±{dz:.3f} | latency {1e3 * est.latency:.0f} ms"
                + (" | STALE" if est.stale else ""))

    def _snapshot(self) -> None:
        if self.snapshot_path is None:  # no out_dir: nothing is written
            return
        self.model.save(self.snapshot_path)
        self._last_snapshot = time.monotonic()

    def _end_message(self) -> str:
        lat = np.asarray(self.latencies)
        p = (f"; latency p50 {1e3 * np.percentile(lat, 50):.1f} ms, p99 {1e3 * np.percentile(lat, 99):.1f} ms"
             if len(lat) else "")
        unused = "; ".join(f"{v} {k}" for k, v in self.unused.items())
        return (f"{self.n_stances} stance(s), {self.n_updates} update(s), {self.intake.received} frame(s) received, "
                f"{self.intake.logged} logged, {self.intake.dropped} not processed" + p
                + (f"; unused: {unused}" if unused else ""))


# Its pieces are modules of their own (intake, estimate, causal_filter, stance, resample; the simulated walk:
# hardware.walking_leg).
# One concept: the live loop (frames in, each stance out, the estimate published, every frame recorded).
