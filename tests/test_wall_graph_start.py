"""No stall lasts (issue 13 item 2): a wheeled loop that never starts (its endpoints never matched) is detected by the
experiment harness within seconds and its nodes are started again, instead of an experiment waiting for learning for
good. The never-started first attempt is declared by the harness (the graph itself starts normally); the restarted
nodes must then run the loop."""
import pytest
from mm_bringup.process_graph import ProcessGraph
from mm_bringup.wall_graph import LOOP_START_ATTEMPTS, WallGraph


class FirstStartFails(WallGraph):
    """The first wait for the loop's first step reports a stall, as if the loop's endpoints had never matched. The
    declared stall takes no real start from the harness: the restarted loop keeps the retries an experiment has
    (a real stall of it is restarted as in any experiment; CI once saw one under load)."""
    stalls = 0
    loop_start_attempts = LOOP_START_ATTEMPTS + 1

    def spin_until(self, predicate, timeout, what):
        if what == 'the lockstep loop to start' and not self.stalls:
            self.stalls += 1
            raise TimeoutError('the loop never started (declared by the test)')
        return super().spin_until(predicate, timeout, what)


def test_a_loop_that_never_started_is_restarted(tmp_path, capsys):
    with FirstStartFails(tmp_path, exploration_steps=300, model_path='') as wall:
        assert wall.stalls == 1 and len(wall.nodes) == 3
        assert all(n.process.poll() is None for n in wall.nodes)
        stopped = [n for n in wall.graph.nodes if n not in wall.nodes]      # the earlier attempts' processes
        assert len(stopped) in (3, 6) and all(n.process.poll() is not None for n in stopped)
        step = wall.state_stamp
        wall.spin_until(lambda: wall.state_stamp > step, 30.0, 'the loop to run on')
    assert 'did not start' in capsys.readouterr().out


class NeverStarts(WallGraph):
    """Every wait for the loop's first step reports a stall; one start only."""
    loop_start_attempts = 1

    def spin_until(self, predicate, timeout, what):
        if what == 'the lockstep loop to start':
            raise TimeoutError('the loop never started (declared by the test)')
        return super().spin_until(predicate, timeout, what)


def test_a_loop_that_never_starts_fails_with_its_nodes_logs_and_leaves_no_node_running(tmp_path):
    """The error of the last failed start carries each node's last log lines (a CI run's work directory is gone),
    and the harness stops what it started before raising."""
    graph = ProcessGraph(log_dir=tmp_path / 'logs')
    with pytest.raises(TimeoutError) as failed:
        NeverStarts(tmp_path, exploration_steps=300, model_path='', graph=graph)
    assert len(graph.nodes) == 3 and not any(graph.running().values())
    text = str(failed.value)
    assert 'after 1 start(s)' in text
    assert all(f'--- {label} (last lines) ---' in text
               for label in ('wheeled_sim', 'switching_controller', 'sensor_manifold'))
