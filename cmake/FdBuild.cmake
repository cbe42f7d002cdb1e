# Build-speed and hygiene settings shared by every target.

# ccache: presets set CMAKE_CXX_COMPILER_LAUNCHER; fall back to it when found.
if(NOT CMAKE_CXX_COMPILER_LAUNCHER)
  find_program(FD_CCACHE ccache)
  if(FD_CCACHE)
    set(CMAKE_C_COMPILER_LAUNCHER "${FD_CCACHE}")
    set(CMAKE_CXX_COMPILER_LAUNCHER "${FD_CCACHE}")
  endif()
endif()

# A fast linker: LibTorch and gRPC binaries are large, and GNU ld spends most
# of an incremental build linking them. Prefer mold, then lld.
include(CheckLinkerFlag)
foreach(_fd_linker mold lld)
  check_linker_flag(CXX "-fuse-ld=${_fd_linker}" FD_HAS_LINKER_${_fd_linker})
  if(FD_HAS_LINKER_${_fd_linker})
    add_link_options("-fuse-ld=${_fd_linker}")
    message(STATUS "FrameDiffuser: linking with ${_fd_linker}")
    break()
  endif()
endforeach()

# fd_target_warnings(<target>): our warning flags, applied per target so that
# generated code and third-party headers (included as system headers) are not
# affected.
function(fd_target_warnings target)
  target_compile_options(${target} PRIVATE -Wall -Wextra -Wno-unused-parameter)
  if(FD_WERROR)
    target_compile_options(${target} PRIVATE -Werror)
  endif()
endfunction()

# fd_add_gtest(<name> SOURCES ... LIBS ...): one GoogleTest binary per
# component, its tests discovered by ctest. Tests run from the build tree and
# get FD_GOLDEN_DIR (unless the environment overrides it) and the source dir.
function(fd_add_gtest name)
  cmake_parse_arguments(ARG "" "" "SOURCES;LIBS;LABELS" ${ARGN})
  add_executable(${name} ${ARG_SOURCES})
  target_link_libraries(${name} PRIVATE ${ARG_LIBS} GTest::gmock GTest::gtest_main)
  target_compile_definitions(${name} PRIVATE
      FD_DEFAULT_GOLDEN_DIR="${FD_GOLDEN_DIR}"
      FD_SOURCE_DIR="${PROJECT_SOURCE_DIR}")
  fd_target_warnings(${name})
  gtest_discover_tests(${name}
      DISCOVERY_TIMEOUT 120
      PROPERTIES LABELS "${ARG_LABELS}")
endfunction()

# libzstd (Debian libzstd-dev): sessions compress exported states, the wire
# API compresses images. Its CMake package is preferred, pkg-config is the
# fallback; found once, GLOBAL, so every folder links the same target through
# ${FD_ZSTD_TARGET}.
find_package(zstd CONFIG QUIET GLOBAL)
if(TARGET zstd::libzstd_shared)
  set(FD_ZSTD_TARGET zstd::libzstd_shared)
else()
  find_package(PkgConfig REQUIRED)
  pkg_check_modules(FD_ZSTD REQUIRED IMPORTED_TARGET GLOBAL libzstd)
  set(FD_ZSTD_TARGET PkgConfig::FD_ZSTD)
endif()
