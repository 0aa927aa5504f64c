"""QoS of the wheeled robot's lockstep loop (ranges, /clock, manifold state, wheel commands), one home for the
simulator, the learner and the controller.

RELIABLE: the controller waits for each step's state and a recorder must not lose a message. RELIABLE only
re-sends what is still in the writer's history, though, and a recorder outside the loop (another host, a loaded
machine) may fall behind the loop by thousands of steps: with depth 50 a multi-host run under load lost three /clock
steps from the bag, and with depth 1000 the demo's recorder, taking the arm's camera frames beside the wheeled loop
at ~900 steps/s, lost about 200 of each Range topic's 12 800 messages. Depth 10 000 holds 5-10 s of the loop at
today's 1 000-2 000 steps/s; the messages are small (< 1 kB), so the history costs at most about 10 MB per topic, and
only while a reader lags. The arm's loop carries 0.5 MB camera frames and keeps its own, shallower profile
(arm_sim_node).
"""
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

LOOP_QOS = QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
