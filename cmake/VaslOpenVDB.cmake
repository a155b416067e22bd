# OpenVDB 10 from Debian: its FindOpenVDB.cmake ships in /usr/lib/x86_64-linux-gnu/cmake/OpenVDB.
# It needs Boost iostreams (libboost-iostreams-dev) and Imath for the half codec.
find_path(OPENVDB_FIND_MODULE FindOpenVDB.cmake
  PATHS /usr/lib/x86_64-linux-gnu/cmake/OpenVDB /usr/lib/cmake/OpenVDB /usr/local/lib/cmake/OpenVDB
  NO_DEFAULT_PATH)
if(OPENVDB_FIND_MODULE)
  list(APPEND CMAKE_MODULE_PATH "${OPENVDB_FIND_MODULE}")
endif()
find_package(OpenVDB REQUIRED)
pkg_check_modules(IMATH REQUIRED IMPORTED_TARGET Imath)
