"""The learner's samples on disk, so a crash of the sensor_manifold node loses none of what was explored.

An append-only text file, one line per sample, flushed at once: a killed process (SIGKILL included) loses at most the
line being written, which the next load drops. No pickle: the first line is a JSON header (format, version, dt), each
further line `stamp_ns,follows,command_left,command_right,r0,r1,r2,r3,r4` - the command that led to the sample, whether
exactly one command did (the chain of consecutive samples), and the five readings (inf: out of range, nan: lost).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, TextIO

import numpy as np

FORMAT = 'mm.sensor_manifold.samples'
VERSION = 1
N_READINGS = 5


@dataclass
class LoadedSamples:
    """What a sample log held: readings (n, 5), the n - 1 commands between them and their chain flags, and what was
    wrong with the lines that could not be used (a sample after a dropped line starts a new chain)."""
    readings: List[np.ndarray] = field(default_factory=list)
    commands: List[np.ndarray] = field(default_factory=list)
    continuous: List[bool] = field(default_factory=list)
    problems: List[str] = field(default_factory=list)


def _parse(line: str) -> np.ndarray:
    values = line.split(',')
    if len(values) != 4 + N_READINGS:
        raise ValueError(f'{len(values)} fields, expected {4 + N_READINGS}')
    row = np.array([float(v) for v in values])
    if not (row[0] >= 0 and row[1] in (0.0, 1.0) and np.all(np.isfinite(row[2:4]))):
        raise ValueError('stamp >= 0, follows 0/1 and a finite command required')
    readings = row[4:]
    if np.any(readings[~np.isnan(readings)] < 0):
        raise ValueError('a reading is negative')
    return row


class SampleLog:
    """Append-only sample file of one learner (`dt` must match the file's, else the file is not this robot's)."""

    def __init__(self, path: str | Path, dt: float):
        self.path, self.dt = Path(path), float(dt)
        self._file: Optional[TextIO] = None

    def load(self) -> LoadedSamples:
        """The samples kept so far (none if there is no file). A file of another format or dt raises ValueError;
        a malformed line is dropped and named in `problems`."""
        out = LoadedSamples()
        if not self.path.exists():
            return out
        with open(self.path, encoding='utf-8') as f:
            lines = f.read().split('\n')
        try:
            header = json.loads(lines[0])
            ok = (isinstance(header, dict) and header.get('format') == FORMAT and header.get('version') == VERSION
                  and isinstance(header.get('dt'), (int, float)) and math.isclose(header['dt'], self.dt))
        except json.JSONDecodeError:
            ok = False
        if not ok:
            raise ValueError(f'{self.path} is not a {FORMAT} v{VERSION} file with dt {self.dt} '
                             f'(header {lines[0][:120]!r})')
        chain_broken = False
        for number, line in enumerate(lines[1:], start=2):
            if not line:
                continue
            try:
                row = _parse(line)
            except ValueError as exc:
                out.problems.append(f'line {number}: {exc}')
                chain_broken = True
                continue
            if out.readings:
                out.commands.append(row[2:4].copy())
                out.continuous.append(bool(row[1]) and not chain_broken)
            out.readings.append(row[4:].copy())
            chain_broken = False
        return out

    def open(self) -> None:
        """Start appending (a new file gets its header)."""
        new = not self.path.exists() or self.path.stat().st_size == 0
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, 'a', encoding='utf-8')
        if new:
            self._file.write(json.dumps({'format': FORMAT, 'version': VERSION, 'dt': self.dt}) + '\n')
        elif not self._ends_with_newline():
            self._file.write('\n')            # a line cut by a crash stays a malformed line of its own
        self._file.flush()

    def _ends_with_newline(self) -> bool:
        with open(self.path, 'rb') as f:
            f.seek(-1, 2)
            return f.read(1) == b'\n'

    def append(self, stamp_ns: int, reading: np.ndarray, command: Optional[np.ndarray], follows: bool) -> None:
        """One sample, flushed to the operating system at once (it survives the process being killed)."""
        u = np.zeros(2) if command is None else command
        values = [str(int(stamp_ns)), '1' if follows else '0'] + [repr(float(v)) for v in (*u, *reading)]
        self._file.write(','.join(values) + '\n')
        self._file.flush()

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
