/// @file world_frame.h
/// @brief The project's origin (VASL-MODEL §1): world coordinates at the facade, lattice
///        coordinates (world − x_0) inside. Georeferenced sites sit at 10⁵-10⁷ m, where a float
///        keeps 0.5 m; beneath the origin the lattice keeps positions in float and binned keys
///        in 21 bits per axis.
/// @details The engine converts at its boundary, and only there: a scan's poses before they are
///          stored (the catalog, the blobs and every flow speak lattice coordinates), a render's
///          or a back-projection's pose, a query's box and the centroids it returns, the poses
///          ListScans returns, and the transforms of an exported file.
#pragma once

#include <Eigen/Core>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "lattice/geometry/pose.h"
#include "lattice/ingest/scan_input.h"
#include "lattice/store/project_store.h"

namespace vasl::flows {

/// Distance from the origin, per axis, that the lattice holds at vossel edge h: ±(2²⁰ − 1)·h
/// (ingest::kMaxVosselIndex). At that distance a float position keeps h/8, so the key range
/// and the float precision run out together: ±21 km at 2 cm, ±5.2 km at 5 mm, ±1.05 km at
/// 1 mm.
double LatticeReachM(double vossel_size_m);

/// §1 *(choice)*: the origin a project created without one takes from its first scan: the
/// scan's position rounded to the nearest kilometre on each axis. A site near the world's
/// origin keeps x_0 = 0; a georeferenced one gets a round origin that a user can read back.
Eigen::Vector3d OriginOfFirstScan(const ingest::ScanInput& scan);

/// `pose` with its position moved by `by` (world → lattice: by = −x_0; back: +x_0).
geometry::Pose Shifted(geometry::Pose pose, const Eigen::Vector3d& by);
/// The scan's and every source's pose moved by `by`.
void ShiftScan(store::ScanInfo& scan, const Eigen::Vector3d& by);

/// OK when every position of `scan` (its pose and its images') lies within LatticeReachM of
/// `origin` on each axis; INVALID_ARGUMENT naming the position, the origin and the reach
/// otherwise (a site beyond the reach needs a project with an origin near it).
absl::Status CheckScanWithinReach(const ingest::ScanInput& scan, const Eigen::Vector3d& origin,
                                  double vossel_size_m);
/// The same for one world position (`what` names it in the message).
absl::Status CheckWithinReach(const Eigen::Vector3d& world_m, const Eigen::Vector3d& origin,
                              double vossel_size_m, const std::string& what);

}  // namespace vasl::flows
