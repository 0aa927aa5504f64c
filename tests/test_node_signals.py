"""Clean shutdown (issue 13 item 7): SIGINT and SIGTERM end every node of a running graph with exit status 0 and no
traceback, whenever they land (mid-spin, mid-publish, while a model is fitted). Each node is signalled several times at
varying moments and restarted in between, while the rest of its graph keeps running."""
import os
import random
import signal
import time

import pytest

from mm_bringup.process_graph import ProcessGraph, wait_for
from mm_common.ros_harness import RosHarness

SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGINT)
SIM_TIME = {'use_sim_time': True}
# Small learning sizes so that fits happen while the signals land.
GRAPHS = {
    'wheeled': [('mm_sim', 'wheeled_sim', {'republish_period': 0.2}),
                ('mm_planner', 'switching_controller', {**SIM_TIME, 'exploration_steps': 300}),
                ('mm_manifold', 'sensor_manifold', {**SIM_TIME, 'learn_after': 300})],
    'arm': [('mm_sim', 'arm_sim', {'republish_period': 0.2}),
            ('mm_planner', 'dp_planner', {**SIM_TIME, 'exploration_steps': 60}),
            ('mm_manifold', 'image_embedding', {**SIM_TIME, 'min_training_frames': 40, 'refit_every': 20})],
}


def _signal_cycles(graph: ProcessGraph, package: str, executable: str, parameters: dict, rng: random.Random) -> list:
    """Signal the running node, check how it ended, restart it; return the failures."""
    failures = []
    node = next(n for n in graph.nodes if n.executable == executable)
    for cycle, sig in enumerate(SIGNALS):
        # Let it work a varying while: some signals land during start-up work, some mid-loop.
        time.sleep(rng.uniform(0.05, 0.5))
        rc, log = node.process.poll(), ''
        if rc is not None:
            failures.append(f'{executable}: died before signal {cycle} with {node.process.returncode}:\n'
                            f'{graph.log_tail(node)}')
        else:
            os.killpg(node.process.pid, sig)
            try:
                rc = node.process.wait(15)
            except Exception:  # noqa: BLE001 - a hang is the finding
                rc = None
            log = node.log_path.read_text(errors='replace')
            if rc != 0 or 'Traceback' in log:
                failures.append(f'{executable}: {signal.Signals(sig).name} #{cycle} -> exit status {rc}'
                                f"{' with a traceback' if 'Traceback' in log else ''}:\n{log[-1500:]}")
            if rc is None:
                graph.stop(node)
        node.log_path.rename(node.log_path.with_name(f'{executable}.{cycle}.log'))
        # Signals before the node's Python imports are done keep Python's defaults (run_node is not running yet):
        # restart only once the old node has left the graph, and signal only once the new one is on it. Seen by a
        # new participant each cycle: the test's own participant, which knew the old node, kept listing it after it
        # had exited (twice, in full fresh-clone runs of the suite: exit status 0, empty log, still listed 30 s later;
        # where the discovery layer lost its farewell was not established); a participant that joins afterwards
        # hears from live participants only (that the old process ended is known from its exit status above).
        probe = RosHarness()
        try:
            seen = probe.node(f'signal_probe_{executable}_{cycle}')
            try:
                wait_for(lambda: executable not in seen.get_node_names(), 30.0, message=f'{executable} to leave')
            except TimeoutError:
                pytest.fail(f'{executable} still on the graph 30 s after {signal.Signals(sig).name} #{cycle} (exit '
                            f'status {rc}); failures so far: {failures}; its log:\n{log[-1500:]}')
            node = graph.start(package, executable, parameters)
            wait_for(lambda: executable in seen.get_node_names() or node.process.poll() is not None, 30.0,
                     message=f'{executable} to restart')
        finally:
            probe.close()
    return failures


@pytest.mark.parametrize('name', sorted(GRAPHS))
def test_every_node_of_a_running_graph_exits_cleanly_on_signals(name, tmp_path):
    rng = random.Random(13)
    ros = RosHarness()
    observer = ros.node(f'signal_observer_{name}')
    failures = []
    # The recorder records the loop (mid-write signals); each restart replaces the bag it wrote.
    nodes = GRAPHS[name] + [('mm_bringup', 'recorder', {'output': str(tmp_path / 'bag'), 'overwrite': True})]
    with ProcessGraph(log_dir=tmp_path / 'logs') as graph:
        for package, executable, parameters in nodes:
            graph.start(package, executable, parameters)
        try:
            assert ros.spin_until(lambda: {e for _, e, _ in nodes} <= set(observer.get_node_names()), 60.0)
            for package, executable, parameters in nodes:
                failures += _signal_cycles(graph, package, executable, parameters, rng)
            for node in [n for n in graph.nodes if n.process.poll() is None]:
                rc = graph.stop(node)
                if rc != 0:
                    failures.append(f'{node.label}: final SIGINT -> {rc}:\n{graph.log_tail(node)}')
        finally:
            ros.close()
    assert not failures, '\n\n'.join(failures)


def test_sigusr1_writes_every_threads_stack_to_the_log_and_the_node_goes_on(tmp_path):
    """node_utils.dump_stacks_on_request: what ProcessGraph.stop sends a node that ignored SIGINT, before SIGTERM.
    The kernel hands a signal sent to the process to any thread that does not block it, which may be one of the DDS
    middleware's: faulthandler then heads every Python thread "Thread 0x..." and none "Current thread 0x..." (which
    this test waited for: the likeliest cause of its one failure in a fresh-clone run). The main thread's stack is in
    the dump either way."""
    with ProcessGraph(log_dir=tmp_path) as graph:
        node = graph.start('mm_sim', 'wheeled_sim', {'republish_period': 0.2})
        wait_for(lambda: 'wheeled_sim ready' in graph.log_tail(node), 30.0, message='wheeled_sim ready')
        os.killpg(node.process.pid, signal.SIGUSR1)
        # the main thread's Python stack, however the dump headed it
        wait_for(lambda: 'in run_nodes' in graph.log_tail(node, lines=200), 10.0, message='the stack dump')
        assert '(most recent call first)' in graph.log_tail(node, lines=200)
        assert node.process.poll() is None
        assert graph.stop(node) == 0
