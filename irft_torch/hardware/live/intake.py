"""The CAN side of the live estimator: the Notifier's one listener, which logs every frame before anything else and
queues it (bounded) for the worker."""

from __future__ import annotations

import copy
import queue
import struct
import threading
import time

import can

__all__ = ["CanIntake"]


class CanIntake(can.Listener):
    """The Notifier's one listener: every frame to the log first (nothing the bus delivered is lost
    from it), then into the bounded queue for the worker; bus errors flagged for the worker."""

    def __init__(self, logger, max_queue: int) -> None:
        self.logger = logger
        self.queue: queue.Queue = queue.Queue(maxsize=max_queue)
        self.received = self.logged = self.dropped = self.error_frames = 0
        self.unnamed_channel = 0  # frames logged without their channel (the log's format cannot hold it)
        self.high_water = 0
        self.error: BaseException | None = None
        self.lock = threading.Lock()
        # wall-clock arrival of the last data frame per CANSimple node (id >> 5): staleness is judged here, as
        # frames arrive, not by the worker (which may be busy with an update)
        self.last_seen: dict[int, float] = {}

    def on_message_received(self, msg: can.Message) -> None:
        now = time.monotonic()
        if self.logger is not None:
            try:
                self.logger.on_message_received(msg)
            except (struct.error, OverflowError):  # a channel the format cannot hold (BLF: a number below 2^16;
                # python-can reads one from a name's trailing digits, "vcan-123456"): logged without it
                unnamed = copy.copy(msg)
                unnamed.channel = None
                self.logger.on_message_received(unnamed)
                self.unnamed_channel += 1
            self.logged += 1
        self.received += 1
        if msg.is_error_frame:
            self.error_frames += 1
        elif not msg.is_remote_frame and not msg.is_extended_id:
            self.last_seen[msg.arbitration_id >> 5] = now
        try:
            self.queue.put_nowait((now, msg))
        except queue.Full:
            self.dropped += 1
        self.high_water = max(self.high_water, self.queue.qsize())

    def on_error(self, exc: Exception) -> None:
        with self.lock:
            if self.error is None:
                self.error = exc
        time.sleep(0.02)  # the Notifier calls recv again at once: do not spin while the worker reconnects

    def stop(self) -> None:  # the Notifier stops its listeners; the log outlives a reconnection
        pass
