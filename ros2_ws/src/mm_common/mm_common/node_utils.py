"""Helpers every mm node shares: the Jazzy main() pattern, parameter declaration with descriptors, parameter
checks for on-set callbacks and throttled logging of rejected input."""
from __future__ import annotations

import faulthandler
import math
import signal
import sys
import threading
import time
import weakref
from typing import Any, Callable, Dict, Iterable, Mapping, Optional, Sequence, Tuple

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.experimental import EventsExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)   # SIGHUP: the terminal closed
STOP_POLL_S = 0.1        # s: longest a stop request waits for an idle executor to return
ACK_WAIT_S = 10.0        # s: longest a stopping process waits for reliable subscribers to acknowledge its messages


def run_node(node_factory: Callable[[], Node], args: Optional[Sequence[str]] = None) -> None:
    """Spin one node until SIGINT/SIGTERM/SIGHUP or external shutdown (run_nodes)."""
    run_nodes([node_factory], args)


def wait_for_acknowledgements(nodes: Sequence[Node], seconds: float) -> None:
    """Before the nodes' publishers go: wait until every reliable subscriber acknowledged what they published, at
    most `seconds` in all. A subscriber that lags behind (a recorder on a busy machine) would otherwise lose the
    messages still on their way: the demo's bag once missed the last 700 steps of five Range topics, stopped before the
    recorder had them. Best-effort publishers need no acknowledgement."""
    deadline = time.monotonic() + seconds
    for node in nodes:
        for publisher in list(node.publishers):
            left = deadline - time.monotonic()
            if left <= 0:
                return
            try:
                publisher.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9)))
            except _rclpy.RCLError:
                return          # the context went away (external shutdown): nothing left to wait for


def dump_stacks_on_request() -> None:
    """`kill -USR1 <pid>` writes every thread's Python stack to the process's stderr (a node's log) and the process
    goes on: what a node that does not stop is doing. faulthandler writes from its own C handler, so this works even
    while the main thread is stuck in C code, where a Python signal handler never runs (a recorder of a fresh-clone
    test run ignored SIGINT and SIGTERM once, README issue 13). ProcessGraph.stop sends it before SIGTERM."""
    faulthandler.register(signal.SIGUSR1, all_threads=True)


def run_nodes(node_factories: Sequence[Callable[[], Node]], args: Optional[Sequence[str]] = None,
              create_when: Optional[Callable[[Sequence[Node]], bool]] = None) -> None:
    """Spin the nodes (one, or several composed in one process) in one executor until SIGINT/SIGTERM/SIGHUP or
    external shutdown, then clean up; the process exits with status 0. Each node is created once `create_when` (if
    given) is true of the nodes created before it, checked as they spin (e.g. a recorder elsewhere subscribed).

    The executor is rclpy's EventsExecutor: the SingleThreadedExecutor rebuilds its wait set from every
    subscription's, publisher's and QoS event's handle on each wait, which cost the wheeled graph's nodes 1.2-2.5 ms
    of CPU per step against 0.55-0.9 ms here, and the graph 40 % of its rate (README, issue 14). Its spin_once
    returns after `STOP_POLL_S` without an event, which is how a stop request is noticed: this EventsExecutor
    supports no guard conditions to wake it.
    rclpy's own signal handlers shut the context down inside the handler, which races with an executor that is
    still working (`RCLError: failed to initialize wait set: the given context is not valid`, exit 1). Here a
    signal only sets a flag (Python runs the handler in the main thread once spin_once has returned), the loop
    ends and, once reliable subscribers acknowledged what the nodes published (wait_for_acknowledgements), the node is
    destroyed before the context is shut down. Further signals during clean-up and exit are
    ignored (SIGKILL still works); signals before the node's imports are done keep Python's defaults.
    A start-up configuration the node refuses (a parameter out of its range, of the wrong type, or a ValueError from
    the constructor) ends the process with one error line and exit status 2 instead of a traceback.
    """
    stop = threading.Event()
    for sig in _STOP_SIGNALS:
        signal.signal(sig, lambda *_: stop.set())
    dump_stacks_on_request()
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    nodes = []
    executor = None
    refused = ''
    try:
        executor = EventsExecutor()
        for node_factory in node_factories:
            while create_when is not None and nodes and not create_when(nodes):
                if stop.is_set() or not rclpy.ok():
                    return
                executor.spin_once(timeout_sec=STOP_POLL_S)
            if stop.is_set():
                return
            try:
                nodes.append(node_factory())
            except (ParameterException, ValueError) as exc:
                refused = f'{getattr(node_factory, "__name__", "node")}: cannot start: {exc}'
                return
            executor.add_node(nodes[-1])
        # rclpy.ok() takes the context's lock: asked after every callback it was 4 % of the composed loop's CPU
        # (py-spy, README issue 14), so an external shutdown is noticed within STOP_POLL_S instead.
        next_ok_check = 0.0
        while not stop.is_set():
            executor.spin_once(timeout_sec=STOP_POLL_S)
            now = time.monotonic()
            if now >= next_ok_check:
                if not rclpy.ok():
                    break
                next_ok_check = now + STOP_POLL_S
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except _rclpy.RCLError:
        if rclpy.ok() and not stop.is_set():
            raise       # a real failure, not the shutdown race
    finally:
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        wait_for_acknowledgements(nodes, ACK_WAIT_S)
        for node in reversed(nodes):
            node.destroy_node()
        rclpy.try_shutdown()
        # Python's finalisation puts SIG_DFL back for signals with a Python handler, so a signal arriving while the
        # interpreter exits would kill the process (status -2, seen under load with a second SIGINT); an ignored
        # signal stays ignored.
        for sig in _STOP_SIGNALS:
            signal.signal(sig, signal.SIG_IGN)
        if refused:
            print(refused, file=sys.stderr)
            raise SystemExit(2)


def publish_if_subscribed(publisher, msg) -> bool:
    """Publish `msg` unless nothing subscribes (it would reach no one; serialising it costs the lockstep loop about
    20 us a message, README issue 14). A subscriber that has not matched yet would miss it either way."""
    if not publisher.get_subscription_count():
        return False
    publisher.publish(msg)
    return True


def declare(node: Node, name: str, default: Any, description: str, *,
            min_value: Optional[float] = None, max_value: Optional[float] = None,
            step: float = 0.0, read_only: bool = False, additional_constraints: str = '') -> Any:
    """Declare a parameter with a descriptor (description and, for numbers, an inclusive range); return its value.

    rclpy itself rejects set requests outside the declared range, so nodes only need an on-set callback for
    constraints a range cannot express (see `reject_non_finite`).
    """
    descriptor = ParameterDescriptor(description=description, read_only=read_only,
                                     additional_constraints=additional_constraints)
    if min_value is not None or max_value is not None:
        lo = -math.inf if min_value is None else min_value
        hi = math.inf if max_value is None else max_value
        if isinstance(default, bool):
            raise TypeError(f'parameter {name}: a range makes no sense for a bool')
        if isinstance(default, int):
            descriptor.integer_range = [IntegerRange(from_value=int(max(lo, -2**63)),
                                                     to_value=int(min(hi, 2**63 - 1)), step=int(step))]
        else:
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi),
                                                                  step=float(step))]
    return node.declare_parameter(name, default, descriptor).value


def _elements(value: Any) -> Iterable[Any]:
    """The elements of an array parameter value (list, tuple or the array.array rclpy hands to on-set callbacks)."""
    if isinstance(value, (str, bytes)) or not hasattr(value, '__iter__'):
        return (value,)
    return value


def reject_non_finite(params) -> SetParametersResult:
    """On-set callback: refuse NaN/inf in any float parameter update or in any element of a float-array update.

    rclpy passes double arrays set at runtime as `array.array('d')`, not lists, so every iterable is checked.
    """
    for p in params:
        scalar = isinstance(p.value, float)
        for i, v in enumerate(_elements(p.value)):
            if isinstance(v, float) and not math.isfinite(v):
                where = p.name if scalar else f'{p.name}[{i}]'
                return SetParametersResult(successful=False, reason=f'{where}: value must be finite, got {v}')
    return SetParametersResult(successful=True)


class _ProposedValues(dict):
    """Parameter values after an update: the update's own values, else the node's current ones (looked up lazily)."""

    def __init__(self, node: Node, params):
        super().__init__((p.name, p.value) for p in params)
        self._node = node

    def get(self, name: str, default: Any = None) -> Any:
        if name in self:
            return self[name]
        return self._node.get_parameter(name).value if self._node.has_parameter(name) else default


def proposed_values(node: Node, params) -> Mapping[str, Any]:
    """The node's parameter values as they would be after `params` is applied (for cross-parameter checks;
    read them with `.get(name)`)."""
    return _ProposedValues(node, params)


def check_parameters(node: Node, params, checks: Sequence[Callable[[Mapping[str, Any]], str]]
                     ) -> SetParametersResult:
    """Run cross-parameter `checks` on the proposed values; each returns '' if fine or the reason it is not.

    Use in an on-set callback: `return check_parameters(self, params, [ordered('a_min', 'a_max')])`.
    """
    result = reject_non_finite(params)
    if not result.successful:
        return result
    values = proposed_values(node, params)
    for check in checks:
        reason = check(values)
        if reason:
            return SetParametersResult(successful=False, reason=reason)
    return SetParametersResult(successful=True)


def ordered(lower: str, upper: str, strict: bool = False) -> Callable[[Mapping[str, Any]], str]:
    """A check for `check_parameters`: parameter `lower` <= (or <, if strict) parameter `upper`."""
    def check(values: Mapping[str, Any]) -> str:
        lo, hi = values.get(lower), values.get(upper)
        if lo is None or hi is None:
            return ''
        if lo > hi or (strict and lo == hi):
            return f"{lower}={lo} must be {'<' if strict else '<='} {upper}={hi}"
        return ''
    return check


def ordered_pair(name: str, strict: bool = True) -> Callable[[Mapping[str, Any]], str]:
    """A check for `check_parameters`: the two-element array parameter `name` is [low, high] with low < high."""
    def check(values: Mapping[str, Any]) -> str:
        pair = values.get(name)
        if pair is None:
            return ''
        pair = list(pair)
        if len(pair) != 2:
            return f'{name} needs two values [low, high], got {len(pair)}'
        if pair[0] > pair[1] or (strict and pair[0] == pair[1]):
            return f"{name}: low {pair[0]} must be {'<' if strict else '<='} high {pair[1]}"
        return ''
    return check


def array_length(name: str, length: int) -> Callable[[Mapping[str, Any]], str]:
    """A check for `check_parameters`: array parameter `name` has exactly `length` elements."""
    def check(values: Mapping[str, Any]) -> str:
        value = values.get(name)
        if value is not None and len(list(value)) != length:
            return f'{name} needs {length} values, got {len(list(value))}'
        return ''
    return check


def reject_read_only(names: Iterable[str]) -> Callable[[Sequence], SetParametersResult]:
    """On-set callback refusing runtime changes of parameters that only take effect at start-up.

    Prefer `declare(..., read_only=True)`; this is for parameters whose descriptor must stay writable (e.g. shared
    descriptors) and reads as: 'dt can only be set at start-up'.
    """
    frozen = frozenset(names)

    def callback(params) -> SetParametersResult:
        for p in params:
            if p.name in frozen:
                return SetParametersResult(successful=False, reason=f'{p.name} can only be set at start-up')
        return SetParametersResult(successful=True)
    return callback


class InputRejections:
    """Counts rejected inputs per source and logs 'rejected input on <source>: <problem>' at most once per
    `period` wall seconds per source (wall time: a stalled sim clock must not silence the log)."""

    def __init__(self, node: Node, period: float = 1.0):
        self.logger = node.get_logger()
        self.period = period
        self.counts: Dict[str, int] = {}
        self._last_log: Dict[str, float] = {}
        self._since_log: Dict[str, int] = {}

    def __call__(self, source: str, problem: str) -> int:
        self.counts[source] = self.counts.get(source, 0) + 1
        self._since_log[source] = self._since_log.get(source, 0) + 1
        now = time.monotonic()
        if now - self._last_log.get(source, -math.inf) >= self.period:
            suppressed = self._since_log[source] - 1
            more = f' (+{suppressed} more since the last report)' if suppressed else ''
            self.logger.warn(f'rejected input on {source}: {problem}{more} [{self.counts[source]} in total]')
            self._last_log[source] = now
            self._since_log[source] = 0
        return self.counts[source]

    @property
    def total(self) -> int:
        return sum(self.counts.values())


_rejections: 'weakref.WeakKeyDictionary[Node, InputRejections]' = weakref.WeakKeyDictionary()


def reject_input(node: Node, source: str, problem: str) -> int:
    """Log (throttled per node and source) that an input was rejected and why; return the count for `source`.

    `source` names the topic or service (`wheeled/wheel_velocity_controller/commands`), `problem` says what was
    wrong with the message (`expected 2 wheel speeds, got 3`).
    """
    rejections = _rejections.get(node)
    if rejections is None:
        rejections = _rejections[node] = InputRejections(node)
    return rejections(source, problem)


def rejected_inputs(node: Node) -> Dict[str, int]:
    """How many inputs `reject_input` has rejected on this node, per source."""
    rejections = _rejections.get(node)
    return dict(rejections.counts) if rejections is not None else {}


def array_problem(values: Sequence[float], what: str, length: Optional[int] = None,
                  bounds: Optional[Tuple[float, float]] = None) -> str:
    """'' if `values` has `length` finite elements within `bounds` (inclusive); else what is wrong with them."""
    n = len(values)
    if length is not None and n != length:
        return f'{what}: expected {length} values, got {n}'
    for i, v in enumerate(values):
        if not math.isfinite(v):
            return f'{what}[{i}] is {v} (must be finite)'
        if bounds is not None and not bounds[0] <= v <= bounds[1]:
            return f'{what}[{i}]={v} outside [{bounds[0]}, {bounds[1]}]'
    return ''


def clock_went_back(now_ns: int, newest_ns: Optional[int], stamp_ns: int) -> bool:
    """Whether a stamp older than the newest one taken is explained by the clock itself having gone back past that
    newest stamp (a simulator restarted from an earlier time, a bag played again): a new timeline to follow, not a
    stale or forged message (those come while the clock runs on, and stay rejected)."""
    return newest_ns is not None and 0 < now_ns < newest_ns and stamp_ns <= now_ns
