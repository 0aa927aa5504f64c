"""A fitted SensorManifoldModel as an mm_msgs/SensorManifoldModel message: what the controller needs to use the
model, on any host, without the learner's files or classes (it reads the message with mm_planner.wall_model)."""
from __future__ import annotations

from typing import Sequence

import numpy as np
from mm_msgs.msg import SensorManifoldModel as ModelMsg

from mm_manifold.sensor_manifold import SensorManifoldModel


def _flat(array) -> list:
    return [float(v) for v in np.asarray(array, dtype=float).ravel()]


def model_to_msg(model: SensorManifoldModel, sensor2_range: Sequence[float]) -> ModelMsg:
    """`sensor2_range`: [min_range, max_range] of the sensor-2 sensors (from their Range messages): the readings a
    goal can be given in."""
    virtual, field2, regions = model.virtual_, model.field2_, model.regions1_
    known = regions.known()
    msg = ModelMsg(format_version=ModelMsg.FORMAT_VERSION, dt=float(model.dt), samples=int(model.n_samples_),
                   excursions=int(model.n_excursions_), dimension=int(model.dimension_), ready=bool(model.ready),
                   readiness=model.readiness() or '', heldout_sensor2_error=float(model.heldout_sensor2_error_),
                   heldout_reentry_error=float(model.heldout_reentry_error_),
                   heldout_limit=float(model.heldout_limit_), heldout_count=int(model.heldout_count_))
    msg.grid_rows, msg.grid_cols = int(model.grid_rows), int(model.grid_cols)
    msg.grid_nodes, msg.grid_mean = _flat(model.grid_.nodes_), _flat(model.grid_.mean_)
    msg.grid_axes, msg.grid_extent = _flat(model.grid_.axes_), _flat(model.grid_.extent_)
    msg.grid_residual = float(model.grid_.residual_)
    msg.jacobian_degree = int(model.jacobian_degree)
    msg.field1_theta, msg.field1_center = _flat(model.field1_.theta_), _flat(model.field1_.center_)
    msg.field1_scale = _flat(model.field1_.scale_)
    msg.virtual_correction = _flat(virtual.field_.correction)
    msg.virtual_bounds = _flat(model.virtual_bounds())
    msg.reentry_rms_before = float(virtual.reentry_rms_before_)
    msg.reentry_rms_after = float(virtual.reentry_rms_after_)
    if field2 is not None:
        msg.field2_theta, msg.field2_center = _flat(field2.theta_), _flat(field2.center_)
        msg.field2_scale = _flat(field2.scale_)
    msg.region_anchors = _flat(regions.anchors_[known])
    msg.region_jacobians = _flat(regions.jacobians_[known])
    if np.all(np.isfinite(model.sensor2_box_)):
        msg.sensor2_box = _flat(model.sensor2_box_)
    msg.sensor2_noise = _flat(model.sensor2_noise_)
    msg.sensor2_range = _flat(sensor2_range)
    msg.route_travel_weight = float(virtual.route_travel_weight)
    msg.goal_neighbors = int(virtual.goal_neighbors)
    msg.overlap_coordinates = _flat(virtual.overlap_coordinates_)
    msg.overlap_sensor2 = _flat(virtual.overlap_sensor2_)
    msg.overlap_exits = _flat(virtual.overlap_exits_)
    msg.overlap_travel = _flat(virtual.overlap_travel_)
    msg.overlap_route = [int(v) for v in virtual.overlap_route_]
    msg.route_lengths = [int(v) for v in virtual.route_lengths_]
    msg.route_commands = _flat(virtual.route_commands_)
    return msg
