"""The wheeled robot's sensor vector, as every node reads it: the five proximity sensors' names (the Range topics
`wheeled/range/<name>`, in reading-vector order) and the two groups of the paper (Section 2.1): sensor 1, the three
front sensors, and sensor 2, the two side sensors. The one home of these constants (simulator, learner, controller
and tools import them); which sensor sees what is the layout's business, not the code's. Also the one place that
writes sensor_msgs/Range messages into an mm_msgs/RangeGroup (`range_group`)."""
from typing import Sequence

from mm_msgs.msg import RangeGroup

SENSOR_NAMES = ('front_left', 'front_center', 'front_right', 'side_front', 'side_rear')
SENSOR1 = (0, 1, 2)   # indices of the front group in the reading vector
SENSOR2 = (3, 4)      # indices of the side group


def range_group(names: Sequence[str], ranges: Sequence) -> RangeGroup:
    """The RangeGroup of `ranges` (sensor_msgs/Range, ranges[i] of names[i]): each Range field as one array. The
    group's header (the step's stamp) is the caller's."""
    return RangeGroup(names=list(names), frame_ids=[r.header.frame_id for r in ranges],
                      radiation_type=[r.radiation_type for r in ranges],
                      field_of_view=[r.field_of_view for r in ranges], min_range=[r.min_range for r in ranges],
                      max_range=[r.max_range for r in ranges], range=[r.range for r in ranges],
                      variance=[r.variance for r in ranges])
