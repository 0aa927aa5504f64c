"""No stall lasts (issue 13 item 2): a wheeled loop that never starts (its endpoints never matched) is detected by the
experiment harness within seconds and its nodes are started again, instead of an experiment waiting for learning for
good. The never-started first attempt is declared by the harness (the graph itself starts normally); the restarted
nodes must then run the loop."""
from mm_bringup.wall_graph import WallGraph


class FirstStartFails(WallGraph):
    """The first wait for the loop's first step reports a stall, as if the loop's endpoints had never matched."""
    stalls = 0

    def spin_until(self, predicate, timeout, what):
        if what == 'the lockstep loop to start' and not self.stalls:
            self.stalls += 1
            raise TimeoutError('the loop never started (declared by the test)')
        return super().spin_until(predicate, timeout, what)


def test_a_loop_that_never_started_is_restarted(tmp_path, capsys):
    with FirstStartFails(tmp_path, exploration_steps=300, model_path='') as wall:
        assert wall.stalls == 1 and len(wall.nodes) == 3
        assert all(n.process.poll() is None for n in wall.nodes)
        stopped = [n for n in wall.graph.nodes if n not in wall.nodes]      # the first attempt's processes
        assert len(stopped) == 3 and all(n.process.poll() is not None for n in stopped)
        step = wall.state_stamp
        wall.spin_until(lambda: wall.state_stamp > step, 30.0, 'the loop to run on')
    assert 'did not start' in capsys.readouterr().out
