/// @file pose.h
/// @brief Rigid poses of scans and cameras (VASL-MODEL §2).
/// @details A pose `T_world_sensor` maps a sensor-frame point `p_sensor` to the world:
///          `x_world = R · p_sensor + o`. World frame is right-handed, z up, metres.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "absl/status/statusor.h"

namespace vasl::geometry {

/// A rigid transform from a sensor frame to the world frame (VASL-MODEL §2).
struct Pose {
  /// Rotation taking sensor-frame directions to world-frame directions (unit quaternion).
  Eigen::Quaterniond q_world_sensor = Eigen::Quaterniond::Identity();
  /// Sensor origin in the world frame, metres.
  Eigen::Vector3d o_world = Eigen::Vector3d::Zero();

  /// Sensor-frame point (metres) to world-frame point (metres).
  Eigen::Vector3d SensorToWorld(const Eigen::Vector3d& p_sensor) const {
    return q_world_sensor * p_sensor + o_world;
  }
  /// World-frame point (metres) to sensor-frame point (metres).
  Eigen::Vector3d WorldToSensor(const Eigen::Vector3d& x_world) const {
    return q_world_sensor.conjugate() * (x_world - o_world);
  }
  /// World-frame direction to sensor-frame direction (no translation).
  Eigen::Vector3d DirectionToSensor(const Eigen::Vector3d& d_world) const {
    return q_world_sensor.conjugate() * d_world;
  }
  /// Sensor-frame direction to world-frame direction (no translation).
  Eigen::Vector3d DirectionToWorld(const Eigen::Vector3d& d_sensor) const {
    return q_world_sensor * d_sensor;
  }
};

/// Builds a pose from a position (metres) and a quaternion given as (x, y, z, w), the order the
/// proto and the scan manifest use. The quaternion is normalised; a non-finite component, or a
/// quaternion whose norm is below 1e-9, is INVALID_ARGUMENT.
absl::StatusOr<Pose> MakePose(const Eigen::Vector3d& position_m, const Eigen::Vector4d& quat_xyzw);

}  // namespace vasl::geometry
