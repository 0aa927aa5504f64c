"""Localhost means localhost: a node started through `./mm` with the default LOCALHOST discovery holds UDP sockets
on the loopback interface only (Fast DDS profile config/fastdds_localhost.xml), and still talks to a peer; SUBNET
and ROS_STATIC_PEERS runs do not get the profile (multi-host use stays available)."""
import ipaddress
import os
import signal
import socket
import struct
import subprocess
from pathlib import Path

import pytest

from mm_bringup.process_graph import dds_environment, wait_for

ROOT = Path(__file__).resolve().parents[1]
MM = ROOT / 'mm'
PROFILE_VARS = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE', 'ROS_AUTOMATIC_DISCOVERY_RANGE',
                'ROS_STATIC_PEERS', 'MM_LOCALHOST_PROFILE', 'MM_DISCOVERY_RANGE')


def _clean_env(**overrides):
    env = {k: v for k, v in os.environ.items() if k not in PROFILE_VARS}
    env.update(overrides)
    return env


def _socket_inodes(pid: int) -> set:
    inodes = set()
    for fd in Path(f'/proc/{pid}/fd').iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith('socket:['):
            inodes.add(int(target[8:-1]))
    return inodes


def _decode_address(hex_address: str) -> str:
    host = hex_address.split(':')[0]
    if len(host) == 8:
        return socket.inet_ntop(socket.AF_INET, struct.pack('<I', int(host, 16)))
    raw = b''.join(struct.pack('<I', int(host[i:i + 8], 16)) for i in range(0, 32, 8))
    return socket.inet_ntop(socket.AF_INET6, raw)


def held_sockets(pid: int) -> list:
    """(protocol, local address, port) of every UDP/TCP socket the process holds (/proc/<pid>/net + fd inodes)."""
    inodes = _socket_inodes(pid)
    held = []
    for proto in ('udp', 'udp6', 'tcp', 'tcp6'):
        table = Path(f'/proc/{pid}/net/{proto}')
        if not table.exists():
            continue
        for line in table.read_text().splitlines()[1:]:
            fields = line.split()
            if int(fields[9]) in inodes:
                held.append((proto, _decode_address(fields[1]), int(fields[1].split(':')[1], 16)))
    return held


def _local_only(address: str) -> bool:
    ip = ipaddress.ip_address(address)
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped:
        ip = ip.ipv4_mapped
    return ip.is_loopback or ip.is_multicast


def _start(env):
    return subprocess.Popen([str(MM), 'run', 'mm_sim', 'wheeled_sim', '--ros-args', '-p', 'lockstep:=false'],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)


def _stop(proc):
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def _environ(pid: int) -> dict:
    raw = Path(f'/proc/{pid}/environ').read_bytes().split(b'\0')
    return dict(item.decode(errors='replace').split('=', 1) for item in raw if b'=' in item)


def test_default_mm_environment_binds_dds_to_loopback_only():
    env = _clean_env()
    proc = _start(env)
    try:
        # The node must still be reachable: a subscriber started the same way receives its /clock.
        echo = subprocess.run([str(MM), 'topic', 'echo', '/clock', '--once', '--timeout', '20'], env=env,
                              capture_output=True, text=True, timeout=60)
        assert echo.returncode == 0 and 'clock' in echo.stdout, echo.stderr[-2000:]
        assert proc.poll() is None
        assert _environ(proc.pid).get('FASTRTPS_DEFAULT_PROFILES_FILE') == str(ROOT / 'config' /
                                                                               'fastdds_localhost.xml')
        sockets = held_sockets(proc.pid)
        udp = [s for s in sockets if s[0].startswith('udp')]
        assert udp, sockets
        exposed = [s for s in sockets if not _local_only(s[1])]
        assert not exposed, f'sockets not on loopback: {exposed} (all: {sockets})'
    finally:
        _stop(proc)


def test_subnet_discovery_is_not_restricted_to_loopback():
    """The contrast that shows the profile is what binds to loopback: with SUBNET the node listens on 0.0.0.0."""
    proc = _start(_clean_env(ROS_AUTOMATIC_DISCOVERY_RANGE='SUBNET'))
    try:
        wait_for(lambda: any(s[0] == 'udp' for s in held_sockets(proc.pid)), 20, message='DDS sockets')
        assert 'FASTRTPS_DEFAULT_PROFILES_FILE' not in _environ(proc.pid)
        assert any(not _local_only(s[1]) for s in held_sockets(proc.pid))
    finally:
        _stop(proc)


@pytest.mark.parametrize('overrides, profiled', [
    ({}, True),
    ({'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}, True),
    ({'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET'}, False),
    ({'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST', 'ROS_STATIC_PEERS': '192.168.1.20'}, False),
    ({'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST', 'FASTRTPS_DEFAULT_PROFILES_FILE': '/my/own.xml'}, 'own'),
], ids=['default', 'localhost', 'subnet', 'static-peers', 'own-profile'])
def test_mm_env_and_process_graph_decide_the_profile_alike(overrides, profiled):
    """./mm (also nested in an ./mm shell) and ProcessGraph children get the profile only for localhost use."""
    ours = str(ROOT / 'config' / 'fastdds_localhost.xml')
    expected_profile = {True: ours, False: None, 'own': '/my/own.xml'}[profiled]
    expected_range = 'SYSTEM_DEFAULT' if profiled is True else overrides['ROS_AUTOMATIC_DISCOVERY_RANGE']

    def decided(env):
        out = subprocess.run([str(MM), 'env'], env=env, capture_output=True, text=True, check=True).stdout
        values = dict(part.split('=', 1) for line in out.splitlines() for part in line.split()[1:] if '=' in part)
        return ({k: v.strip("'") for k, v in values.items()})

    fresh = decided(_clean_env(**overrides))
    assert fresh.get('FASTRTPS_DEFAULT_PROFILES_FILE') == expected_profile
    assert fresh['ROS_AUTOMATIC_DISCOVERY_RANGE'] == expected_range
    # Started from inside an ./mm shell (its decision inherited) with these settings of its own: decided again.
    outer = _clean_env()
    outer.update({k: v for k, v in decided(outer).items() if k in PROFILE_VARS})
    nested_env = dict(outer, **overrides)
    if 'FASTRTPS_DEFAULT_PROFILES_FILE' not in overrides and profiled != 'own':
        nested_env['FASTRTPS_DEFAULT_PROFILES_FILE'] = ours
    nested = decided(nested_env)
    assert nested.get('FASTRTPS_DEFAULT_PROFILES_FILE') == expected_profile
    assert nested['ROS_AUTOMATIC_DISCOVERY_RANGE'] == expected_range
    graph_child = dds_environment(nested_env)
    assert graph_child.get('FASTRTPS_DEFAULT_PROFILES_FILE') == expected_profile
    assert graph_child['ROS_AUTOMATIC_DISCOVERY_RANGE'] == expected_range
