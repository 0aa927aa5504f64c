"""Fuzzing every input of every node (issue 13): each node runs as a real process and gets hostile messages on every
topic it subscribes to, hostile requests on every service it offers and hostile values for every parameter, then a
valid input; it must stay up, answer, and still process the valid input. Failures name node, input and variant.

For a message (or service request) template, `message_variants` yields copies with one field made hostile at a
time: NaN/inf/1e308 in floats, empty, one-too-short/long and huge sequences, extreme integers, empty/huge/path-like
strings, stamps far in the future (2^31-1 s), at zero, negative or with an invalid nanosecond field (and, after the
first valid frame, stamps going backwards). `NodeFuzzer` starts the node (mm_bringup.process_graph), discovers the
topics it subscribes to and the services it offers from the ROS graph, sends every variant, then a valid input, and
records every crash (restarting the node to go on), every request left unanswered, every valid input no longer
processed, and every non-finite parameter value accepted.
"""
from __future__ import annotations

import copy
import importlib
import math
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from mm_msgs.msg import (CollisionMap, Contact, EmbeddingState, ManifoldState, RangeGroup, SensorGoal,
                        SensorManifoldModel)
from mm_msgs.srv import PlaceObject, ResetPose, SetJointGoal, SetSensorGoal
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import Parameter as ParameterMsg, ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, ListParameters, SetParameters
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image, JointState, Range
from std_msgs.msg import Bool, Float64MultiArray, Header, String

from mm_bringup.process_graph import NodeProcess, ProcessGraph
from mm_common.rosbag import iter_messages
from mm_common.ros_harness import RosHarness
from mm_common.wheeled_sensors import range_group
from mm_sim.arm_model import ArmModel

FAR_FUTURE_SEC = 2**31 - 1
HUGE_LENGTH = 100_000
# Topics every rclpy node subscribes to or serves for rcl itself, not the node's own inputs.
SYSTEM_TOPICS = {'/parameter_events', '/clock', '/rosout'}
PARAMETER_SERVICES = ('describe_parameters', 'get_parameter_types', 'get_parameters', 'list_parameters',
                      'set_parameters', 'set_parameters_atomically', 'get_type_description')
# Parameters rcl itself declares; flipping them changes the node's time base, not its input handling.
SYSTEM_PARAMETERS = {'use_sim_time', 'start_type_description_service', 'qos_overrides'}

INT_LIMITS = {'int8': (-2**7, 2**7 - 1), 'uint8': (0, 2**8 - 1), 'byte': (0, 255), 'octet': (0, 255),
              'char': (0, 255), 'int16': (-2**15, 2**15 - 1), 'uint16': (0, 2**16 - 1),
              'int32': (-2**31, 2**31 - 1), 'uint32': (0, 2**32 - 1), 'int64': (-2**63, 2**63 - 1),
              'uint64': (0, 2**64 - 1)}


def get_message(type_name: str):
    """The Python class of 'pkg/msg/Type' (graph spelling) or 'pkg/Type' (field spelling)."""
    parts = type_name.split('/')
    package, kind, name = (parts[0], 'msg', parts[1]) if len(parts) == 2 else parts
    return getattr(importlib.import_module(f'{package}.{kind}'), name)


def get_service(type_name: str):
    package, _, name = type_name.split('/')
    return getattr(importlib.import_module(f'{package}.srv'), name)


def _float_variants(ftype: str) -> List[Tuple[str, float]]:
    huge = 3.4e38 if ftype == 'float' else 1e308
    return [('nan', math.nan), ('inf', math.inf), ('-inf', -math.inf), ('huge', huge), ('-huge', -huge),
            ('negative', -1.0)]


def _sequence_variants(element: str, value) -> List[Tuple[str, object]]:
    current = list(value)
    n = max(len(current), 1)
    if element in ('double', 'float'):
        huge = 3.4e38 if element == 'float' else 1e308
        out = [('empty', []), ('all-nan', [math.nan] * n), ('all-inf', [math.inf] * n), ('all-huge', [huge] * n),
               ('one-too-long', current + [0.0]), (f'length-{HUGE_LENGTH}', [0.0] * HUGE_LENGTH)]
        if current:
            out.append(('one-too-short', current[:-1]))
        return out
    if element == 'boolean':
        return [('empty', []), ('one-too-long', current + [True]), (f'length-{HUGE_LENGTH}', [True] * HUGE_LENGTH)]
    if element in ('uint8', 'octet', 'byte', 'char'):
        return [('empty', b''), ('half', bytes(len(current) // 2)), ('one-too-long', bytes(len(current) + 1)),
                ('2MB', bytes(2_000_000))]
    if element in INT_LIMITS:
        lo, hi = INT_LIMITS[element]
        return [('empty', []), ('all-max', [hi] * n), ('all-min', [lo] * n), ('one-too-long', current + [0])]
    if element == 'string':
        return [('empty', []), ('1000-strings', ['x'] * 1000)]
    return [('empty', [])]          # sequences of messages: empty; longer ones are built from default messages


def _leaf_variants(ftype: str, value) -> List[Tuple[str, object]]:
    if ftype in ('double', 'float'):
        return _float_variants(ftype)
    if ftype in INT_LIMITS:
        lo, hi = INT_LIMITS[ftype]
        return [('max', hi), ('min', lo)]
    if ftype == 'boolean':
        return [('flipped', not value)]
    if ftype.startswith('string'):
        return [('empty', ''), ('64KiB', 'x' * 65536), ('path-escape', '../../../../etc/passwd'),
                ('control-chars', 'rgb8\x00\x01')]
    if ftype.startswith('sequence<') and ftype.endswith('>'):
        element = ftype[len('sequence<'):-1].split(',')[0]
        if '/' in element:
            cls = get_message(element)
            return [('empty', []), ('1000-defaults', [cls() for _ in range(1000)])]
        return _sequence_variants(element, value)
    if '[' in ftype and ftype.endswith(']'):           # fixed-size array: keep the size, poison the values
        element = ftype[:ftype.index('[')]
        if element in ('double', 'float'):
            return [('all-nan', [math.nan] * len(value)), ('all-inf', [math.inf] * len(value))]
    return []


def _stamp_variants() -> List[Tuple[str, Tuple[int, int]]]:
    return [('far-future', (FAR_FUTURE_SEC, 0)), ('zero', (0, 0)), ('negative', (-1, 0)),
            ('nanosec-overflow', (0, 2**32 - 1))]


def message_variants(template, prefix: str = '') -> Iterator[Tuple[str, object]]:
    """(description, copy of `template` with one field made hostile) for every leaf field, recursively."""
    for name, ftype in template.get_fields_and_field_types().items():
        value = getattr(template, name)
        path = f'{prefix}{name}'
        if ftype == 'builtin_interfaces/Time':
            for what, (sec, nanosec) in _stamp_variants():
                msg = copy.deepcopy(template)
                stamp = getattr(msg, name)
                stamp.sec, stamp.nanosec = sec, nanosec
                yield f'{path}={what}', msg
            continue
        if '/' in ftype and not ftype.startswith('sequence<') and '[' not in ftype:
            for what, nested in message_variants(value, f'{path}.'):
                msg = copy.deepcopy(template)
                setattr(msg, name, nested)
                yield what, msg
            continue
        for what, poisoned in _leaf_variants(ftype, value):
            msg = copy.deepcopy(template)
            try:
                setattr(msg, name, poisoned)
            except (AssertionError, TypeError, ValueError):
                continue            # the Python binding itself refuses it: nothing can be sent
            yield f'{path}={what}', msg


def stamp_of(msg) -> Optional[int]:
    header = getattr(msg, 'header', None)
    if header is None:
        return None
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


@dataclass
class NodeSpec:
    """What to start and how to tell that it still works.

    frame(k): the valid inputs of step k (topic, message), in publication order, with stamps that grow with k.
    processed(k, received): whether the node's output `output` shows frame k was processed (received: every output
    message so far, in order). templates / requests: bases for the variants of inputs not in a frame, and the valid
    request of each service (a default request if missing). extra: hand-written malformed inputs per topic.
    """
    package: str
    executable: str
    frame: Callable[[int], List[Tuple[str, object]]]
    output: Tuple[str, type]
    processed: Callable[[int, list, int], bool]
    parameters: Dict[str, object] = field(default_factory=dict)
    templates: Dict[str, object] = field(default_factory=dict)
    requests: Dict[str, object] = field(default_factory=dict)
    extra: Dict[str, List[Tuple[str, object]]] = field(default_factory=dict)
    before_frame: Callable[[int], List[Tuple[str, object]]] = lambda k: []


@dataclass
class Failure:
    input: str
    variant: str
    what: str
    log: str = ''

    def line(self) -> str:
        return f'{self.input} | {self.variant} | {self.what}'


RELIABLE = ReliabilityPolicy.RELIABLE


class NodeFuzzer:
    """Drives one node process; `run()` returns the failures (empty when the node withstood everything)."""

    def __init__(self, spec: NodeSpec, work: Path, per_service_timeout: float = 5.0,
                 processed_timeout: float = 15.0):
        self.spec = spec
        self.work = Path(work)
        self.graph = ProcessGraph(log_dir=self.work / 'logs')
        self.ros = RosHarness()
        self.client = self.ros.node(f'fuzz_driver_{spec.executable}')
        self.proc: Optional[NodeProcess] = None
        self.failures: List[Failure] = []
        self.sent = 0
        self.restarts = 0
        self.frame_index = 0
        self.received: list = []
        self.service_timeout = per_service_timeout
        self.processed_timeout = processed_timeout
        self.publishers: Dict[str, object] = {}
        self.clients: Dict[str, object] = {}
        topic, msg_type = spec.output
        self.client.create_subscription(msg_type, topic, self.received.append,
                                        QoSProfile(depth=1000, reliability=RELIABLE))

    # --- process ------------------------------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return self.spec.executable

    def alive(self) -> bool:
        return self.proc is not None and self.proc.process.poll() is None

    def start(self) -> None:
        if self.proc is not None and self.proc.log_path is not None and self.proc.log_path.exists():
            # The graph writes <node>.log again: keep the log of the run that ended.
            self.proc.log_path.rename(self.proc.log_path.with_name(f'{self.name}.run{self.restarts}.log'))
        self.proc = self.graph.start(self.spec.package, self.spec.executable, self.spec.parameters)
        if not self.ros.spin_until(lambda: self.name in self.client.get_node_names() or not self.alive(), 30.0):
            raise RuntimeError(f'{self.name} did not appear on the graph:\n{self.graph.log_tail(self.proc)}')
        if not self.alive():
            raise RuntimeError(f'{self.name} exited at start-up:\n{self.graph.log_tail(self.proc)}')

    def log(self) -> str:
        return self.graph.log_tail(self.proc, 40) if self.proc else ''

    def _crashed(self, input_name: str, variant: str) -> bool:
        """After a send: if the node died, record it, restart it and report True."""
        if self.alive():
            return False
        rc = self.proc.process.returncode
        self.failures.append(Failure(input_name, variant, f'process exited with status {rc}', self.log()))
        self.restarts += 1
        self.start()
        self._connect()
        return True

    # --- discovery ----------------------------------------------------------------------------------------------
    def inputs(self) -> Tuple[Dict[str, str], Dict[str, str]]:
        """The node's own input topics and services {name: type} as the ROS graph reports them."""
        subs = self.client.get_subscriber_names_and_types_by_node(self.name, '/')
        services = self.client.get_service_names_and_types_by_node(self.name, '/')
        topics = {t: types[0] for t, types in subs if t not in SYSTEM_TOPICS}
        own = {s: types[0] for s, types in services
               if not any(s.endswith('/' + p) for p in PARAMETER_SERVICES)}
        return topics, own

    def _wait_inputs(self) -> Tuple[Dict[str, str], Dict[str, str]]:
        wanted = {('/' + t if not t.startswith('/') else t) for t, _ in self.spec.frame(0)}
        found: Dict[str, Tuple[Dict[str, str], Dict[str, str]]] = {}

        def complete() -> bool:
            found['io'] = self.inputs()
            return wanted <= set(found['io'][0])
        if not self.ros.spin_until(complete, 20.0):
            raise RuntimeError(f'{self.name} never subscribed to {sorted(wanted - set(found["io"][0]))}')
        self.ros.spin_for(0.5)            # late endpoints (services) settle
        return self.inputs()

    def _publisher(self, topic: str, type_name: str):
        if topic not in self.publishers:
            infos = self.client.get_subscriptions_info_by_topic(topic)
            durable = any(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
            qos = QoSProfile(depth=2000, history=HistoryPolicy.KEEP_LAST, reliability=RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL if durable else DurabilityPolicy.VOLATILE)
            self.publishers[topic] = self.client.create_publisher(get_message(type_name), topic, qos)
        return self.publishers[topic]

    def _connect(self) -> None:
        topics, services = self._wait_inputs()
        self.topics, self.services = topics, services
        for topic, type_name in topics.items():
            pub = self._publisher(topic, type_name)
            self.ros.spin_until(lambda: pub.get_subscription_count() > 0, 10.0)
        for service, type_name in services.items():
            if service not in self.clients:
                self.clients[service] = self.client.create_client(get_service(type_name), service)
            self.clients[service].wait_for_service(timeout_sec=5.0)

    # --- sending ------------------------------------------------------------------------------------------------
    def publish(self, topic: str, msg) -> None:
        topic = topic if topic.startswith('/') else '/' + topic
        self._publisher(topic, self.topics.get(topic) or _type_name(msg)).publish(msg)
        self.sent += 1

    def send_frame(self) -> bool:
        """Publish the next valid frame and wait until the node's output shows it was processed."""
        self.frame_index += 1
        k = self.frame_index
        for topic, msg in self.spec.before_frame(k):
            self.publish(topic, msg)
        before = len(self.received)
        for topic, msg in self.spec.frame(k):
            self.publish(topic, msg)
        return self.ros.spin_until(lambda: self.spec.processed(k, self.received, before) or not self.alive(),
                                   self.processed_timeout) and self.alive()

    def fuzz_topic(self, topic: str, type_name: str) -> None:
        bare = topic.lstrip('/')
        template = next((m for t, m in self.spec.frame(0) if t.lstrip('/') == bare), None)
        if template is None:
            template = self.spec.templates.get(bare) or get_message(type_name)()
        variants = list(message_variants(template)) + list(self.spec.extra.get(bare, []))
        for what, msg in variants:
            self.publish(topic, msg)
            self.ros.spin_for(0.005)
            if self._crashed(topic, what):
                continue
        self.ros.spin_for(0.3)
        if self._crashed(topic, '(one of the variants above, detected late)'):
            return
        if not self.send_frame():
            if not self._crashed(topic, 'valid frame after the variants'):
                self.failures.append(Failure(topic, 'valid frame after the variants',
                                             'not processed (no output for it)', self.log()))
                self._recover()

    def _recover(self) -> None:
        """A node that stopped processing is restarted so the next input is judged on its own."""
        self.graph.stop(self.proc)
        self.restarts += 1
        self.start()
        self._connect()

    def call(self, service: str, request) -> Optional[object]:
        future = self.clients[service].call_async(request)
        self.sent += 1
        self.ros.spin_until(lambda: future.done() or not self.alive(), self.service_timeout)
        return future.result() if future.done() else None

    def fuzz_service(self, service: str, type_name: str) -> None:
        srv = get_service(type_name)
        bare = service.lstrip('/')
        valid = self.spec.requests.get(bare) or srv.Request()
        for what, request in message_variants(valid):
            answer = self.call(service, request)
            if self._crashed(service, what):
                continue
            if answer is None:
                self.failures.append(Failure(service, what, f'no response within {self.service_timeout} s'))
        answer = self.call(service, valid)
        if not self._crashed(service, 'valid request') and answer is None:
            self.failures.append(Failure(service, 'valid request', 'no response'))

    # --- parameters ---------------------------------------------------------------------------------------------
    def _parameter_call(self, srv_type, suffix: str, request):
        name = f'/{self.name}/{suffix}'
        key = f'param:{suffix}'
        if key not in self.clients:
            self.clients[key] = self.client.create_client(srv_type, name)
            self.clients[key].wait_for_service(timeout_sec=5.0)
        future = self.clients[key].call_async(request)
        self.sent += 1
        self.ros.spin_until(lambda: future.done() or not self.alive(), self.service_timeout)
        return future.result() if future.done() else None

    def fuzz_parameters(self) -> None:
        listed = self._parameter_call(ListParameters, 'list_parameters', ListParameters.Request())
        if listed is None:
            self.failures.append(Failure('parameters', 'list_parameters', 'no response'))
            return
        names = [n for n in listed.result.names if n.split('.')[0] not in SYSTEM_PARAMETERS]
        current = self._parameter_call(GetParameters, 'get_parameters', GetParameters.Request(names=names))
        if current is None:
            self.failures.append(Failure('parameters', 'get_parameters', 'no response'))
            return
        for name, value in zip(names, current.values):
            for what, bad, non_finite in _parameter_variants(value):
                answer = self._parameter_call(SetParameters, 'set_parameters', SetParameters.Request(
                    parameters=[ParameterMsg(name=name, value=bad)]))
                if self._crashed(f'parameter {name}', what):
                    break
                if answer is None:
                    self.failures.append(Failure(f'parameter {name}', what, 'no response'))
                elif answer.results[0].successful:
                    if non_finite:
                        self.failures.append(Failure(f'parameter {name}', what, 'non-finite value accepted'))
                    # Put the old value back so later inputs meet the node as configured.
                    self._parameter_call(SetParameters, 'set_parameters', SetParameters.Request(
                        parameters=[ParameterMsg(name=name, value=value)]))
        if not self.send_frame() and not self._crashed('parameters', 'valid frame after parameter updates'):
            self.failures.append(Failure('parameters', 'valid frame after parameter updates', 'not processed',
                                         self.log()))
            self._recover()

    # --- whole run ----------------------------------------------------------------------------------------------
    def run(self) -> List[Failure]:
        self.start()
        self._connect()
        if not self.send_frame():
            raise RuntimeError(f'{self.name} did not process a valid frame before any fuzzing:\n{self.log()}')
        for topic, type_name in sorted(self.topics.items()):
            self.fuzz_topic(topic, type_name)
        for service, type_name in sorted(self.services.items()):
            self.fuzz_service(service, type_name)
        self.fuzz_parameters()
        rc = self.graph.stop(self.proc)
        log = self.proc.log_path.read_text(errors='replace') if self.proc.log_path.exists() else ''
        if rc != 0:
            self.failures.append(Failure('SIGINT', 'after fuzzing', f'exit status {rc}', log[-3000:]))
        if 'Traceback' in log:
            self.failures.append(Failure('log', 'after fuzzing', 'traceback in the log', log[-3000:]))
        return self.failures

    def close(self) -> None:
        self.graph.stop_all()
        self.ros.close()


def _type_name(msg) -> str:
    module = type(msg).__module__.split('.')
    return f'{module[0]}/{module[1]}/{type(msg).__name__}'


def _parameter_variants(value: ParameterValue) -> List[Tuple[str, ParameterValue, bool]]:
    """(description, hostile value, whether it is non-finite) for a parameter of the type `value` has."""
    t = value.type
    out: List[Tuple[str, ParameterValue, bool]] = []
    if t == ParameterType.PARAMETER_DOUBLE:
        for what, v in (('nan', math.nan), ('inf', math.inf), ('-inf', -math.inf)):
            out.append((what, ParameterValue(type=t, double_value=v), True))
        for what, v in (('1e308', 1e308), ('-1e308', -1e308), ('negative', -1.0), ('zero', 0.0)):
            out.append((what, ParameterValue(type=t, double_value=v), False))
    elif t == ParameterType.PARAMETER_INTEGER:
        for what, v in (('int64-max', 2**63 - 1), ('int64-min', -2**63), ('zero', 0), ('negative', -1)):
            out.append((what, ParameterValue(type=t, integer_value=v), False))
    elif t == ParameterType.PARAMETER_STRING:
        for what, v in (('empty', ''), ('64KiB', 'x' * 65536), ('path-escape', '../../../../etc/passwd')):
            out.append((what, ParameterValue(type=t, string_value=v), False))
    elif t == ParameterType.PARAMETER_DOUBLE_ARRAY:
        n = max(len(value.double_array_value), 1)
        out.append(('element-nan', ParameterValue(type=t, double_array_value=[math.nan] * n), True))
        out.append(('element-inf', ParameterValue(type=t, double_array_value=[math.inf] * n), True))
        out.append(('empty', ParameterValue(type=t, double_array_value=[]), False))
        out.append(('element-1e308', ParameterValue(type=t, double_array_value=[1e308] * n), False))
        out.append(('one-too-long', ParameterValue(type=t, double_array_value=list(value.double_array_value)
                                                   + [0.0]), False))
    elif t == ParameterType.PARAMETER_INTEGER_ARRAY:
        n = max(len(value.integer_array_value), 1)
        out.append(('empty', ParameterValue(type=t, integer_array_value=[]), False))
        out.append(('element-max', ParameterValue(type=t, integer_array_value=[2**63 - 1] * n), False))
    elif t == ParameterType.PARAMETER_STRING_ARRAY:
        out.append(('empty', ParameterValue(type=t, string_array_value=[]), False))
        out.append(('bad-regex', ParameterValue(type=t, string_array_value=['(', '[a-']), False))
    if t != ParameterType.PARAMETER_STRING:
        out.append(('wrong-type-string', ParameterValue(type=ParameterType.PARAMETER_STRING, string_value='x'), False))
    return out


def report(name: str, failures: Sequence[Failure], sent: int) -> str:
    lines = [f'{name}: {len(failures)} failure(s) after {sent} inputs']
    lines += ['  ' + f.line() for f in failures]
    logs = [f for f in failures if f.log]
    if logs:
        lines += ['', f'log of the first failure ({logs[0].input} | {logs[0].variant}):', logs[0].log[-2500:]]
    return '\n'.join(lines)


# ---------------------------------------------------------------------------------------------------------------------
# The nodes: valid inputs of step k, and how their output shows that step was processed.
# ---------------------------------------------------------------------------------------------------------------------

BASE_NS = 1000 * 1_000_000_000           # valid stamps start at 1000 s of sim time
STEP_NS = 50_000_000


def _time(k: int) -> Time:
    ns = BASE_NS + k * STEP_NS
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _header(k: int, frame_id: str = '') -> Header:
    return Header(stamp=_time(k), frame_id=frame_id)


def _stamped_output(k: int, received: list, before: int) -> bool:
    want = BASE_NS + k * STEP_NS
    return any(stamp_of(m) == want for m in received[before:])


def _any_output(k: int, received: list, before: int) -> bool:
    return len(received) > before


WHEELED_SENSORS = (('front_left', 1.5), ('front_center', 1.5), ('front_right', 1.5), ('side_front', 0.25),
                   ('side_rear', 0.25))


def _ranges(k: int) -> list:
    out = []
    for name, max_range in WHEELED_SENSORS:
        reading = 0.5 if max_range > 1.0 else math.inf
        out.append((f'wheeled/range/{name}', Range(header=_header(k, f'{name}_link'), radiation_type=Range.INFRARED,
                                                   field_of_view=0.05, min_range=0.005, max_range=max_range,
                                                   range=reading)))
    return out


def _range_group(k: int) -> RangeGroup:
    group = range_group([name for name, _ in WHEELED_SENSORS], [msg for _, msg in _ranges(k)])
    group.header = _header(k)
    return group


def _manifold_state(k: int) -> ManifoldState:
    return ManifoldState(header=_header(k), active_space=ManifoldState.SPACE_NONE, coordinates=[],
                         sensor1=[0.5, 0.5, 0.5], sensor2=[math.inf, math.inf], sensor2_estimate=[],
                         sensor1_range=[0.005, 1.5],
                         in_range=[True, True, True, False, False], model_ready=False, samples=k,
                         manifold_dimension=0)


def _image(k: int) -> Image:
    size = 400
    ramp = (np.arange(size * size * 3, dtype=np.uint32) * 7 + k) % 251
    return Image(header=_header(k, 'camera'), height=size, width=size, encoding='rgb8', is_bigendian=0,
                 step=size * 3, data=ramp.astype(np.uint8).tobytes())


def _joints(k: int) -> JointState:
    return JointState(header=_header(k), name=['shoulder_roll', 'shoulder_pitch'],
                      position=[ARM_START[0] + 0.001 * (k % 10), ARM_START[1]])


ARM_START = (-2.0, 1.1)        # inside the arm's joint limits [-3.2, -0.8] x [0.0, 2.2]
# What arm_sim latches on arm/robot_description; sent before every frame (the node ignores a repeat of the same box).
ARM_DESCRIPTION = String(data=ArmModel().robot_description(4.0))
GOAL = SensorGoal(sensor_group=SensorGoal.SENSOR2, reading=[0.2, 0.2], tolerance=0.01)

SPECS = {
    'wheeled_sim': NodeSpec(
        'mm_sim', 'wheeled_sim', parameters={'republish_period': 60.0},
        frame=lambda k: [('wheeled/wheel_velocity_controller/commands', Float64MultiArray(data=[1.0, 1.0]))],
        output=('wheeled/ground_truth/odom', Odometry), processed=_any_output,
        requests={'wheeled/reset': ResetPose.Request(x=0.0, y=0.5, theta=0.0)}),
    'sensor_manifold': NodeSpec(
        'mm_manifold', 'sensor_manifold',
        frame=lambda k: _ranges(k) + [('wheeled/wheel_velocity_controller/commands',
                                       Float64MultiArray(data=[1.0, 1.0]))],
        output=('wheeled/manifold/state', ManifoldState), processed=_stamped_output),
    'sensor_manifold_grouped': NodeSpec(
        'mm_manifold', 'sensor_manifold', parameters={'range_input': 'grouped'},
        frame=lambda k: [('wheeled/ranges', _range_group(k)), ('wheeled/wheel_velocity_controller/commands',
                                                              Float64MultiArray(data=[1.0, 1.0]))],
        output=('wheeled/manifold/state', ManifoldState), processed=_stamped_output),
    'switching_controller': NodeSpec(
        'mm_planner', 'switching_controller',
        frame=lambda k: [('wheeled/bumper', Bool(data=False)), ('wheeled/manifold/state', _manifold_state(k))],
        output=('wheeled/wheel_velocity_controller/commands', Float64MultiArray), processed=_any_output,
        templates={'wheeled/goal': GOAL, 'wheeled/manifold/model': SensorManifoldModel(header=_header(0))},
        requests={'wheeled/set_goal': SetSensorGoal.Request(goal=GOAL)},
        extra={'wheeled/goal': [('reading=[50, 50] m (beyond the sensors)', SensorGoal(
            sensor_group=SensorGoal.SENSOR2, reading=[50.0, 50.0], tolerance=0.01))]}),
    'arm_sim': NodeSpec(
        'mm_sim', 'arm_sim', parameters={'republish_period': 60.0},
        frame=lambda k: [('arm/joint_position_controller/commands',
                          Float64MultiArray(data=[ARM_START[0] + 0.01 * (k % 5), ARM_START[1]]))],
        output=('arm/joint_states', JointState), processed=_any_output,
        requests={'arm/place_object': PlaceObject.Request(random=True)}),
    'image_embedding': NodeSpec(
        'mm_manifold', 'image_embedding',
        frame=lambda k: [('arm/camera/image_raw', _image(k)), ('arm/joint_states', _joints(k)),
                         ('arm/contact', Contact(header=_header(k), in_contact=False))],
        output=('arm/embedding/state', EmbeddingState), processed=_stamped_output,
        before_frame=lambda k: [('arm/robot_description', ARM_DESCRIPTION)],
        templates={'arm/embedding/map_request': _header(0), 'arm/robot_description': ARM_DESCRIPTION},
        extra={'arm/camera/image_raw': [
            ('1x1 image', Image(header=_header(0), height=1, width=1, encoding='rgb8', step=3, data=b'\x00\x00\x00')),
            ('step smaller than width', Image(header=_header(0), height=400, width=400, encoding='rgb8', step=10,
                                              data=bytes(400 * 400 * 3))),
            ('mono8 of rgb8 size', Image(header=_header(0), height=400, width=400, encoding='mono8', step=400,
                                         data=bytes(400 * 400 * 3)))]}),
    'dp_planner': NodeSpec(
        'mm_planner', 'dp_planner',
        frame=lambda k: [('arm/joint_states', _joints(k)), ('arm/contact', Contact(header=_header(k))),
                         ('arm/embedding/state', EmbeddingState(header=_header(k), keypoints_detected=20))],
        output=('arm/joint_position_controller/commands', Float64MultiArray), processed=_any_output,
        before_frame=lambda k: [('arm/robot_description', ARM_DESCRIPTION)],
        templates={'arm/goal': Float64MultiArray(data=[-1.5, 1.5]),
                   'arm/embedding/collision_map': CollisionMap(header=_header(0)),
                   'arm/robot_description': ARM_DESCRIPTION},
        requests={'arm/set_goal': SetJointGoal.Request(positions=[-1.5, 1.5])},
        extra={'arm/embedding/collision_map': [('joint0_limits=[-3.2]', CollisionMap(
            header=_header(0), rows=2, cols=2, joint0_limits=[-3.2], joint1_limits=[0.0, 1.0],
            collision=[False] * 4))]}),
}


@pytest.mark.parametrize('node', sorted(SPECS))
def test_node_survives_malformed_inputs(node, tmp_path):
    """Every input topic, service and parameter of the node gets hostile values; it stays up and keeps working."""
    fuzzer = NodeFuzzer(SPECS[node], tmp_path)
    try:
        failures = fuzzer.run()
    finally:
        fuzzer.close()
    print(f'{node}: {fuzzer.sent} inputs on {sorted(fuzzer.topics)} + {sorted(fuzzer.services)} + parameters, '
          f'{fuzzer.restarts} restart(s)')
    assert not failures, report(node, failures, fuzzer.sent)


# ---------------------------------------------------------------------------------------------------------------------
# Recorder and player: the recorder's inputs are whatever is published; the player's are bags and parameters.
# ---------------------------------------------------------------------------------------------------------------------
FUZZ_TOPICS = {'/fuzz/range': _ranges(0)[1][1], '/fuzz/image': _image(0), '/fuzz/state': _manifold_state(0),
               '/fuzz/model': SensorManifoldModel(header=_header(0))}
VALID_TOPIC = '/fuzz/valid'


def _record(ros: RosHarness, client, graph: ProcessGraph, bag: Path, fuzz: bool) -> Tuple[NodeProcess, int, list]:
    """Run a recorder into `bag`; optionally fuzz it; publish 5 valid messages; stop it. Returns (process, exit
    status, failures)."""
    failures: List[Failure] = []
    recorder = graph.start('mm_bringup', 'recorder', {'output': str(bag), 'discovery_period': 0.05})
    qos = QoSProfile(depth=2000, reliability=RELIABLE)
    topics = dict(FUZZ_TOPICS, **{VALID_TOPIC: Float64MultiArray(data=[1.0, 2.0])}) if fuzz else \
        {VALID_TOPIC: Float64MultiArray(data=[1.0, 2.0])}
    pubs = {t: client.create_publisher(type(m), t, qos) for t, m in topics.items()}
    # Two types on one topic name (from two participants: DDS refuses both in one): the recorder must go on.
    other = RosHarness() if fuzz else None
    conflict = [client.create_publisher(Float64MultiArray, '/fuzz/conflict', qos),
                other.node('fuzz_conflicting_type').create_publisher(Bool, '/fuzz/conflict', qos)] if fuzz else []

    def subscribed() -> bool:
        return all(any(i.node_name == 'recorder' for i in client.get_subscriptions_info_by_topic(t)) for t in pubs)
    if not ros.spin_until(lambda: subscribed() or recorder.process.poll() is not None, 30.0):
        failures.append(Failure('recorder', 'start', 'never subscribed to the published topics',
                                graph.log_tail(recorder)))
    sent = 0
    if fuzz:
        for topic, template in FUZZ_TOPICS.items():
            for what, msg in message_variants(template):
                pubs[topic].publish(msg)
                sent += 1
                ros.spin_for(0.002)
                if recorder.process.poll() is not None:
                    failures.append(Failure(topic, what, f'recorder exited with {recorder.process.returncode}',
                                            graph.log_tail(recorder)))
                    return recorder, recorder.process.returncode, failures
        conflict[0].publish(Float64MultiArray(data=[1.0]))
        conflict[1].publish(Bool(data=True))
    for i in range(5):
        pubs[VALID_TOPIC].publish(Float64MultiArray(data=[float(i), 2.0]))
    ros.spin_for(1.0)
    rc = graph.stop(recorder)
    if other is not None:
        other.close()
    return recorder, rc, failures


def test_recorder_survives_malformed_messages(tmp_path):
    """Hostile messages on many topics (and two types on one topic) are recorded or skipped; the valid messages are
    in a readable bag after SIGINT."""
    ros = RosHarness()
    client = ros.node('fuzz_recorder_driver')
    graph = ProcessGraph(log_dir=tmp_path / 'logs')
    try:
        recorder, rc, failures = _record(ros, client, graph, tmp_path / 'bag', fuzz=True)
        log = recorder.log_path.read_text(errors='replace')
        if rc != 0:
            failures.append(Failure('SIGINT', 'after fuzzing', f'exit status {rc}', log[-3000:]))
        if 'Traceback' in log:
            failures.append(Failure('log', 'after fuzzing', 'traceback in the log', log[-3000:]))
        try:
            valid = [m for m in iter_messages(tmp_path / 'bag', [VALID_TOPIC])]
            if len(valid) != 5:
                failures.append(Failure(VALID_TOPIC, 'valid messages', f'{len(valid)} of 5 in the bag'))
        except Exception as exc:  # noqa: BLE001 - any failure to read the bag is the finding
            failures.append(Failure('bag', 'read after fuzzing', f'{type(exc).__name__}: {exc}'))
    finally:
        graph.stop_all()
        ros.close()
    assert not failures, report('recorder', failures, 0)


def _broken_copies(valid: Path, root: Path) -> Dict[str, Path]:
    """Copies of a valid bag, each damaged in one way."""
    mcap = next(valid.glob('*.mcap'))
    out = {}

    def copy_as(name: str) -> Path:
        target = root / name
        shutil.copytree(valid, target)
        return target
    out['mcap empty (0 bytes)'] = copy_as('empty')
    (out['mcap empty (0 bytes)'] / mcap.name).write_bytes(b'')
    out['mcap truncated to half'] = copy_as('truncated')
    (out['mcap truncated to half'] / mcap.name).write_bytes(mcap.read_bytes()[:mcap.stat().st_size // 2])
    out['mcap random bytes'] = copy_as('garbage')
    (out['mcap random bytes'] / mcap.name).write_bytes(os.urandom(mcap.stat().st_size))
    out['metadata.yaml missing'] = copy_as('no_metadata')
    (out['metadata.yaml missing'] / 'metadata.yaml').unlink()
    out['metadata.yaml not YAML'] = copy_as('bad_metadata')
    (out['metadata.yaml not YAML'] / 'metadata.yaml').write_text('rosbag2_bagfile_information: {{{\n')
    out['metadata.yaml a list'] = copy_as('list_metadata')
    (out['metadata.yaml a list'] / 'metadata.yaml').write_text('- 1\n- 2\n')
    escape = copy_as('path_escape')
    text = (escape / 'metadata.yaml').read_text().replace(mcap.name, '../../../../etc/hostname')
    (escape / 'metadata.yaml').write_text(text)
    out['relative_file_paths outside the bag'] = escape
    out['bag directory missing'] = root / 'does_not_exist'
    return out


def _play(ros: RosHarness, graph: ProcessGraph, bag: Path, parameters: Optional[dict] = None,
          timeout: float = 60.0):
    """Run the player to its end (spinning, so what it plays is received); (exit status or None if hung, log)."""
    player = graph.start('mm_bringup', 'player', {'bag': str(bag), 'rate': 0.0, 'start_delay': 0.3,
                                                   **(parameters or {})})
    if not ros.spin_until(lambda: player.process.poll() is not None, timeout):
        graph.stop(player)
        return None, player.log_path.read_text(errors='replace')
    return player.process.returncode, player.log_path.read_text(errors='replace')


def test_player_rejects_broken_bags_and_bad_parameters_then_plays_a_valid_bag(tmp_path):
    """Every damaged bag or bad parameter ends the player with a non-zero status and a message, never a traceback
    or a hang; the valid bag then plays completely."""
    ros = RosHarness()
    client = ros.node('fuzz_player_driver')
    graph = ProcessGraph(log_dir=tmp_path / 'logs')
    failures: List[Failure] = []
    try:
        valid = tmp_path / 'valid'
        _, rc, recorded = _record(ros, client, graph, valid, fuzz=False)
        assert rc == 0 and not recorded, recorded
        cases = [(what, bag, {}) for what, bag in _broken_copies(valid, tmp_path / 'broken').items()]
        cases += [(f'parameter {name}={value}', valid, {name: value}) for name, value in
                  (('rate', math.nan), ('rate', -1.0), ('rate', 1e308), ('start_delay', math.inf),
                   ('topics', ['(unclosed']))]
        for what, bag, parameters in cases:
            rc, log = _play(ros, graph, bag, parameters)
            if rc is None:
                failures.append(Failure('player', what, 'still running after 60 s', log[-1500:]))
            elif 'Traceback' in log:
                failures.append(Failure('player', what, f'traceback (exit status {rc})', log[-1500:]))
            elif rc == 0 and not parameters:
                failures.append(Failure('player', what, 'exit status 0 for a bag it could not play', log[-1500:]))
        received: list = []
        client.create_subscription(Float64MultiArray, VALID_TOPIC, received.append,
                                   QoSProfile(depth=100, reliability=RELIABLE))
        # starts once the subscription above has matched (a fixed delay was once too short under a loaded gate)
        rc, log = _play(ros, graph, valid, {'start_delay': 30.0, 'wait_for_subscribers': 1})
        ros.spin_until(lambda: len(received) >= 5, 10.0)
        if rc != 0 or len(received) != 5:
            failures.append(Failure('player', 'valid bag', f'exit status {rc}, {len(received)} of 5 received',
                                    log[-1500:]))
    finally:
        graph.stop_all()
        ros.close()
    assert not failures, report('player', failures, 0)
