# Cross-compiling for arm64 (a Raspberry Pi-class light node host) with Debian's cross toolchain
# (g++-aarch64-linux-gnu) against a sysroot of Debian's arm64 -dev packages: scripts/cross-build makes both and
# passes the sysroot in STAGE_SYSROOT (the environment, so that CMake's try_compile projects see it too). Programs
# (protoc, grpc_cpp_plugin) are the build host's; libraries, headers and package files come from the sysroot only.
set(CMAKE_SYSTEM_NAME Linux)
set(CMAKE_SYSTEM_PROCESSOR aarch64)
set(CMAKE_LIBRARY_ARCHITECTURE aarch64-linux-gnu)
set(CMAKE_C_COMPILER aarch64-linux-gnu-gcc)
set(CMAKE_CXX_COMPILER aarch64-linux-gnu-g++)
if(NOT DEFINED ENV{STAGE_SYSROOT})
  message(FATAL_ERROR "aarch64-linux-gnu.cmake: set STAGE_SYSROOT to the arm64 sysroot (scripts/cross-build makes one)")
endif()
set(CMAKE_SYSROOT $ENV{STAGE_SYSROOT})
set(CMAKE_FIND_ROOT_PATH_MODE_PROGRAM NEVER)
set(CMAKE_FIND_ROOT_PATH_MODE_LIBRARY ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_INCLUDE ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_PACKAGE ONLY)
set(ENV{PKG_CONFIG_SYSROOT_DIR} "${CMAKE_SYSROOT}")
set(ENV{PKG_CONFIG_LIBDIR}
    "${CMAKE_SYSROOT}/usr/lib/aarch64-linux-gnu/pkgconfig:${CMAKE_SYSROOT}/usr/share/pkgconfig")
# Tests (and gtest_discover_tests) run under qemu-user, the sysroot as the loader's root.
set(CMAKE_CROSSCOMPILING_EMULATOR qemu-aarch64 -L ${CMAKE_SYSROOT})
