"""Simulators of the mm experiments: a differential-drive robot with five proximity sensors near a wall, and a 2-joint planar arm seen by a camera."""
