/// @file point_attributes.h
/// @brief Internal types shared by the records module's PointDataGrid writers and readers
///        (record_grid.cc: records; geometry_grid.cc: geometry and fused tile objects).
/// @details Not part of the public API (namespace vasl::records::internal).
#pragma once

#include <openvdb/points/AttributeArray.h>

namespace vasl::records::internal {

/// An attribute array that holds its values as they are, no codec (a registered OpenVDB 10
/// type for int8/16/32, float, double and Vec3f: RECORDS-NOTES pitfall 1).
template <typename T>
using RawArray = openvdb::points::TypedAttributeArray<T, openvdb::points::NullCodec>;

/// A type passed as a value, for generic lambdas: `fn(Tag<T>{})`, then
/// `typename decltype(tag)::type`.
template <typename T>
struct Tag {
  using type = T;
};

}  // namespace vasl::records::internal
