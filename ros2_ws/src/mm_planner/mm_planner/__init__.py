"""Controllers of mm: exploration and sensor-switching Jacobian control for the wheeled robot, dynamic-programming planner for the arm."""
