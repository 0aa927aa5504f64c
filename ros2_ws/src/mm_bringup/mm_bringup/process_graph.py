"""Start and stop a set of installed mm nodes as separate processes (what a launch file does, without `launch`).

`launch` is not pip-installable here, so the demo, the multi-process tests and the benchmarks start nodes through
this module. It runs the same `lib/<package>/<executable>` files that `ros2 run` runs, with `--ros-args`.
"""
from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Mapping, Optional, Sequence

from ament_index_python.packages import get_package_prefix


def executable_path(package: str, executable: str) -> Path:
    """The file `ros2 run <package> <executable>` would start."""
    path = Path(get_package_prefix(package)) / 'lib' / package / executable
    if not os.access(path, os.X_OK):
        raise FileNotFoundError(f'no executable {executable!r} in package {package!r} ({path})')
    return path


def ros_args(parameters: Optional[Mapping[str, object]] = None, remappings: Optional[Mapping[str, str]] = None,
             name: Optional[str] = None, params_file: Optional[str] = None, log_level: Optional[str] = None) -> List[str]:
    """Build a `--ros-args ...` list from Python values."""
    args: List[str] = ['--ros-args']
    if name:
        args += ['-r', f'__node:={name}']
    if params_file:
        args += ['--params-file', str(params_file)]
    for key, value in (parameters or {}).items():
        args += ['-p', f'{key}:={_param_literal(value)}']
    for src, dst in (remappings or {}).items():
        args += ['-r', f'{src}:={dst}']
    if log_level:
        args += ['--log-level', log_level]
    return args


def _param_literal(value: object) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, (list, tuple)):
        return '[' + ','.join(_param_literal(v) for v in value) + ']'
    if isinstance(value, str):
        return f"'{value}'"
    return repr(value)


def dds_environment(env: Mapping[str, str]) -> Dict[str, str]:
    """`env` with the loopback-only Fast DDS profile decided for this process exactly as `./mm` decides it.

    `./mm` names the profile in MM_LOCALHOST_PROFILE and, with LOCALHOST discovery and no static peers, applies it
    under ROS_AUTOMATIC_DISCOVERY_RANGE=SYSTEM_DEFAULT (rmw_fastrtps would add a UDP transport on every interface
    for LOCALHOST; the profile does localhost discovery itself), keeping the intent in MM_DISCOVERY_RANGE. A graph
    started from an ./mm shell with SUBNET or ROS_STATIC_PEERS in its own `env` must not inherit the profile; a
    profile file the caller chose is left alone.
    """
    out = dict(env)
    ours = out.get('MM_LOCALHOST_PROFILE')
    if not ours:
        return out
    if out.get('FASTRTPS_DEFAULT_PROFILES_FILE') == ours:
        del out['FASTRTPS_DEFAULT_PROFILES_FILE']
        if out.get('ROS_AUTOMATIC_DISCOVERY_RANGE') == 'SYSTEM_DEFAULT':
            out['ROS_AUTOMATIC_DISCOVERY_RANGE'] = out.get('MM_DISCOVERY_RANGE', 'SYSTEM_DEFAULT')
    out['MM_DISCOVERY_RANGE'] = out.get('ROS_AUTOMATIC_DISCOVERY_RANGE', '')
    localhost = out.get('ROS_AUTOMATIC_DISCOVERY_RANGE') == 'LOCALHOST' and not out.get('ROS_STATIC_PEERS')
    if localhost and not out.get('FASTRTPS_DEFAULT_PROFILES_FILE') and not out.get('FASTDDS_DEFAULT_PROFILES_FILE'):
        out['FASTRTPS_DEFAULT_PROFILES_FILE'] = ours
        out['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'SYSTEM_DEFAULT'
    return out


def _die_with_parent() -> None:
    """Runs in the child before exec: Linux sends it SIGTERM when the process that started it dies, so a crashed or
    killed test/demo never leaves nodes behind that keep talking on the domain (the recorder still finalises)."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(1, signal.SIGTERM)          # PR_SET_PDEATHSIG


@dataclass
class NodeProcess:
    package: str
    executable: str
    parameters: Dict[str, object] = field(default_factory=dict)
    remappings: Dict[str, str] = field(default_factory=dict)
    extra_args: List[str] = field(default_factory=list)
    name: Optional[str] = None
    process: Optional[subprocess.Popen] = None
    log_path: Optional[Path] = None

    @property
    def label(self) -> str:
        return self.name or self.executable


class ProcessGraph:
    """A group of node processes sharing one environment; stops them all with SIGINT (then SIGKILL) on exit."""

    def __init__(self, log_dir: Optional[os.PathLike] = None, env: Optional[Mapping[str, str]] = None):
        self.log_dir = Path(log_dir) if log_dir else None
        self.env = dict(os.environ if env is None else env)
        self.nodes: List[NodeProcess] = []

    def start(self, package: str, executable: str, parameters: Optional[Mapping[str, object]] = None,
              remappings: Optional[Mapping[str, str]] = None, name: Optional[str] = None,
              extra_args: Sequence[str] = ()) -> NodeProcess:
        node = NodeProcess(package, executable, dict(parameters or {}), dict(remappings or {}), list(extra_args), name)
        cmd = [str(executable_path(package, executable)), *node.extra_args,
               *ros_args(node.parameters, node.remappings, name=name)]
        if self.log_dir:
            self.log_dir.mkdir(parents=True, exist_ok=True)
            node.log_path = self.log_dir / f'{node.label}.log'
            out = open(node.log_path, 'wb')
        else:
            out = subprocess.DEVNULL
        # Own process group, so a SIGINT aimed at this graph never reaches the caller (pytest, make).
        node.process = subprocess.Popen(cmd, env=dds_environment(self.env), stdout=out, stderr=subprocess.STDOUT,
                                        stdin=subprocess.DEVNULL, start_new_session=True,
                                        preexec_fn=_die_with_parent if os.name == 'posix' else None)
        if out is not subprocess.DEVNULL:
            out.close()
        self.nodes.append(node)
        return node

    def running(self) -> Dict[str, bool]:
        return {n.label: n.process is not None and n.process.poll() is None for n in self.nodes}

    def stop(self, node: NodeProcess, timeout: float = 10.0) -> Optional[int]:
        """SIGINT like Ctrl-C in `ros2 launch`, escalate to SIGTERM then SIGKILL; return the exit code. Before
        escalating, SIGUSR1 has the node write every thread's stack to its log (node_utils.dump_stacks_on_request):
        where a node that ignored SIGINT is stuck."""
        proc = node.process
        if proc is None:
            return None
        escalation = ((signal.SIGINT, timeout), (signal.SIGUSR1, 1.0), (signal.SIGTERM, 3.0), (signal.SIGKILL, 3.0))
        for sig, wait in escalation:
            if proc.poll() is not None:
                break
            try:
                os.killpg(proc.pid, sig)
            except ProcessLookupError:
                break
            try:
                proc.wait(wait)
            except subprocess.TimeoutExpired:
                continue
        return proc.poll()

    def stop_all(self, timeout: float = 10.0) -> Dict[str, Optional[int]]:
        return {n.label: self.stop(n, timeout) for n in reversed(self.nodes)}

    def log_tail(self, node: NodeProcess, lines: int = 30) -> str:
        if node.log_path is None or not node.log_path.exists():
            return ''
        return '\n'.join(node.log_path.read_text(errors='replace').splitlines()[-lines:])

    def __enter__(self) -> 'ProcessGraph':
        return self

    def __exit__(self, *exc) -> None:
        self.stop_all()


def wait_for(predicate, timeout: float, interval: float = 0.05, message: str = 'condition') -> None:
    """Poll `predicate` until it is true or raise TimeoutError after `timeout` seconds (no fixed sleeps)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(interval)
    raise TimeoutError(f'timed out after {timeout:.1f} s waiting for {message}')
