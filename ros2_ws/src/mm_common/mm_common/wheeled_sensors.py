"""The wheeled robot's sensor vector, as every node reads it: the five proximity sensors' names (the Range topics
`wheeled/range/<name>`, in reading-vector order) and the two groups of the paper (Section 2.1): sensor 1, the three
front sensors, and sensor 2, the two side sensors. The one home of these constants (simulator, learner, controller
and tools import them); which sensor sees what is the layout's business, not the code's."""

SENSOR_NAMES = ('front_left', 'front_center', 'front_right', 'side_front', 'side_rear')
SENSOR1 = (0, 1, 2)   # indices of the front group in the reading vector
SENSOR2 = (3, 4)      # indices of the side group
