"""One sample per simulator step from the messages as they arrive: the sensor_manifold node's rule, in a plain class
so that a bag replay rebuilds the samples with the very same rule (tests/test_wall_graph.py).

A step is complete once every sensor's reading of its stamp came (a bit per sensor: while subscriptions match one by
one at start-up, a re-sent step brings some sensors twice). The command that moved the robot to a step travels on
another topic and may arrive after the step's readings: a complete step with no command since the previous sample
waits for it, for as long as it takes. It stops waiting when the simulator shows that no command will come: it
re-publishes that step (it does so only after a period without a command) or publishes a newer one. A sample follows
its predecessor (a Jacobian pair) only when exactly one command came between them. A step re-published after it was
taken is no new sample. The first sample of a run (or after the clock went back) follows no command.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, List, Optional

import numpy as np

MAX_PENDING_STEPS = 64       # incomplete steps kept while their other readings are on the way


@dataclass
class Sample:
    reading: np.ndarray                # (n_sensors,) REP 117 values: inf out of range, nan lost
    stamp_ns: int
    command: Optional[np.ndarray]      # the newest command since the previous sample (None: none came)
    follows: bool                      # exactly one command since the previous sample


@dataclass
class Resent:
    """A step that was already a sample came again (its state may be sent again for a late joiner)."""
    stamp_ns: int


class SampleAssembler:
    """Feed `reading` and `command` in arrival order; each returns the events it completed (Sample, Resent)."""

    def __init__(self, n_sensors: int = 5, max_pending: int = MAX_PENDING_STEPS):
        self.n_sensors, self.max_pending = n_sensors, max_pending
        self.all_sensors = (1 << n_sensors) - 1
        self.pending: Dict[int, List[float]] = {}          # stamp -> readings + bitmask of the sensors that came
        self.commands_since_sample: List[np.ndarray] = []
        self.waiting: Optional[tuple] = None                # (reading, stamp_ns) of a sample waiting for its command
        self.last_sample_ns: Optional[int] = None          # stamp of the newest sample of this run

    def command(self, u: np.ndarray) -> list:
        self.commands_since_sample.append(np.asarray(u, dtype=float))
        if self.waiting is None:
            return []
        waiting, self.waiting = self.waiting, None
        return [self._sample(*waiting)]

    def reading(self, index: int, stamp_ns: int, value: float) -> list:
        values = self.pending.setdefault(stamp_ns, [math.nan] * self.n_sensors + [0])
        values[index] = value
        values[-1] |= 1 << index
        if len(self.pending) > self.max_pending:
            del self.pending[min(self.pending)]
        if values[-1] != self.all_sensors:
            return []
        del self.pending[stamp_ns]
        for old in [s for s in self.pending if s < stamp_ns]:      # incomplete older steps never complete
            del self.pending[old]
        if self.last_sample_ns is not None and stamp_ns <= self.last_sample_ns:
            # A re-published step: already a sample. The simulator re-sends a step only after a period without a
            # command, and the command that produced a step left before the step did: a sample still waiting for
            # its command gets none (a reset).
            if self.waiting is not None and stamp_ns == self.last_sample_ns:
                waiting, self.waiting = self.waiting, None
                return [self._sample(*waiting)]
            return [] if self.waiting is not None else [Resent(stamp_ns)]
        first_of_run = self.last_sample_ns is None
        self.last_sample_ns = stamp_ns
        reading = np.asarray(values[:-1], dtype=float)
        events = []
        if self.waiting is not None:                         # the earlier sample's command will not come any more
            waiting, self.waiting = self.waiting, None
            events.append(self._sample(*waiting))
        if not self.commands_since_sample and not first_of_run:
            self.waiting = (reading, stamp_ns)
        else:
            events.append(self._sample(reading, stamp_ns))
        return events

    def new_timeline(self) -> list:
        """The clock went back past the newest sample (a restarted simulator): a waiting sample is taken as it is
        and what follows starts a new chain."""
        events = []
        if self.waiting is not None:
            waiting, self.waiting = self.waiting, None
            events.append(self._sample(*waiting))
        self.pending.clear()
        self.commands_since_sample = []
        self.last_sample_ns = None
        return events

    def _sample(self, reading: np.ndarray, stamp_ns: int) -> Sample:
        commands, self.commands_since_sample = self.commands_since_sample, []
        return Sample(reading, stamp_ns, commands[-1] if commands else None, len(commands) == 1)
