# vasl_add_test(NAME SOURCES... [LIBS ...]): one GoogleTest executable, discovered by ctest.
# Tests read real data through VASL_DATA_DIR (default ../shared/data beside the checkout).
set(VASL_DATA_DIR "${CMAKE_SOURCE_DIR}/../shared/data" CACHE PATH "Real scans and panoramas for tests")
function(vasl_add_test name)
  cmake_parse_arguments(ARG "" "" "SOURCES;LIBS" ${ARGN})
  add_executable(${name} ${ARG_SOURCES})
  target_link_libraries(${name} PRIVATE GTest::gtest_main ${ARG_LIBS})
  gtest_discover_tests(${name}
    DISCOVERY_TIMEOUT 60
    PROPERTIES ENVIRONMENT "VASL_DATA_DIR=${VASL_DATA_DIR};VASL_BINARY_DIR=${CMAKE_BINARY_DIR}")
endfunction()
