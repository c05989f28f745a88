# Helpers shared by every folder: warnings for FaStage's own code, and unit tests with CTest labels.

# Warnings on for our own targets only; generated and third-party code is compiled without them.
function(stage_warnings target)
  target_compile_options(${target} PRIVATE -Wall -Wextra -Wpedantic -Wshadow=local -Wnon-virtual-dtor
                                           -Wno-unused-parameter
                                           -Wno-missing-field-initializers)  # designated initializers keep defaults
  if(STAGE_WARNINGS_AS_ERRORS)
    target_compile_options(${target} PRIVATE -Werror)
  endif()
endfunction()

# stage_library(NAME SOURCES ... DEPS ...): a static library with include/ as its public include directory.
function(stage_library name)
  cmake_parse_arguments(ARG "" "" "SOURCES;DEPS;PRIVATE_DEPS" ${ARGN})
  add_library(${name} STATIC ${ARG_SOURCES})
  if(EXISTS ${CMAKE_CURRENT_SOURCE_DIR}/include)
    target_include_directories(${name} PUBLIC ${CMAKE_CURRENT_SOURCE_DIR}/include)
  endif()
  target_include_directories(${name} PRIVATE ${CMAKE_CURRENT_SOURCE_DIR})
  target_link_libraries(${name} PUBLIC ${ARG_DEPS} PRIVATE ${ARG_PRIVATE_DEPS})
  stage_warnings(${name})
endfunction()

# stage_module(NAME SOURCES ... DEPS ...): a plugin module (stage/common/module.h) that programs open when they first
# need it: lib<NAME>.so in build/lib (beside build/bin and build/tests, where OpenModule looks), its own symbols hidden
# but its extern "C" entry point (a library's headers may still mark theirs visible: torch's templates), every symbol
# resolved when it is linked.
function(stage_module name)
  cmake_parse_arguments(ARG "" "" "SOURCES;DEPS" ${ARGN})
  add_library(${name} MODULE ${ARG_SOURCES})
  target_include_directories(${name} PRIVATE ${CMAKE_CURRENT_SOURCE_DIR}/src)
  target_link_libraries(${name} PRIVATE ${ARG_DEPS})
  set_target_properties(${name} PROPERTIES PREFIX "lib" LIBRARY_OUTPUT_DIRECTORY ${CMAKE_BINARY_DIR}/lib
                                           CXX_VISIBILITY_PRESET hidden VISIBILITY_INLINES_HIDDEN ON)
  target_link_options(${name} PRIVATE -Wl,-z,defs)
  stage_warnings(${name})
endfunction()

# stage_program(NAME SOURCES ... DEPS ...): one thin executable.
function(stage_program name)
  cmake_parse_arguments(ARG "" "" "SOURCES;DEPS" ${ARGN})
  add_executable(${name} ${ARG_SOURCES})
  target_include_directories(${name} PRIVATE ${CMAKE_CURRENT_SOURCE_DIR})
  target_link_libraries(${name} PRIVATE ${ARG_DEPS})
  stage_warnings(${name})
endfunction()

# stage_test(NAME SOURCES ... DEPS ... LABELS ... [TIMEOUT s]): a GoogleTest binary registered with CTest, each
# test case its own CTest test so failures are reported by name.
function(stage_test name)
  if(NOT STAGE_BUILD_TESTS)
    return()
  endif()
  cmake_parse_arguments(ARG "" "TIMEOUT" "SOURCES;DEPS;LABELS;PROPERTIES" ${ARGN})
  add_executable(${name} ${ARG_SOURCES})
  target_include_directories(${name} PRIVATE ${CMAKE_CURRENT_SOURCE_DIR})
  target_link_libraries(${name} PRIVATE ${ARG_DEPS} GTest::gtest GTest::gmock GTest::gtest_main)
  set_target_properties(${name} PROPERTIES RUNTIME_OUTPUT_DIRECTORY ${CMAKE_BINARY_DIR}/tests)
  stage_warnings(${name})
  if(NOT ARG_TIMEOUT)
    set(ARG_TIMEOUT 120)
  endif()
  set(env "FASTAGE_BIN_DIR=${CMAKE_BINARY_DIR}/bin")
  # OpenMP's threads (libtorch, Open3D) wait passively: spinning, they take the cores of a busy machine from the
  # threads they wait for (stage::ExecWithPassiveOpenMp does the same for the programs). A property of its own:
  # gtest_discover_tests cannot pass a list through.
  set(omp "OMP_WAIT_POLICY=set:PASSIVE")
  list(LENGTH ARG_LABELS label_count)
  if(label_count GREATER 1)
    # gtest_discover_tests cannot pass a list-valued property (several labels) through; such suites run as one
    # CTest test, and GoogleTest's output names each failing case.
    add_test(NAME ${name} COMMAND ${name})
    set_tests_properties(${name} PROPERTIES LABELS "${ARG_LABELS}" TIMEOUT ${ARG_TIMEOUT} ENVIRONMENT "${env}"
                                            ENVIRONMENT_MODIFICATION "${omp}"
                                            ${ARG_PROPERTIES})
  else()
    include(GoogleTest)
    gtest_discover_tests(${name}
      PROPERTIES LABELS "${ARG_LABELS}" TIMEOUT ${ARG_TIMEOUT} ENVIRONMENT "${env}" ENVIRONMENT_MODIFICATION "${omp}"
                 ${ARG_PROPERTIES}
      DISCOVERY_TIMEOUT 30)
  endif()
endfunction()

# stage_embed_file(TARGET VAR FILE): compiles FILE's text into TARGET as `extern const char VAR[]`.
function(stage_embed_file target var file)
  set(out ${CMAKE_CURRENT_BINARY_DIR}/embedded_${var}.cc)
  add_custom_command(
    OUTPUT ${out}
    COMMAND ${CMAKE_COMMAND} -DIN=${file} -DOUT=${out} -DVAR=${var} -P ${PROJECT_SOURCE_DIR}/cmake/EmbedFile.cmake
    DEPENDS ${file} ${PROJECT_SOURCE_DIR}/cmake/EmbedFile.cmake
    COMMENT "Embedding ${file}")
  target_sources(${target} PRIVATE ${out})
endfunction()

# stage_embed_binary(TARGET VAR FILE): assembles FILE's bytes into TARGET (the assembler's .incbin: no text round
# trip, fast for megabytes) as `extern const unsigned char VAR[]` and `extern const unsigned char VAR_end[]`.
function(stage_embed_binary target var file)
  string(FIND "${file}" "\"" quote)
  string(FIND "${file}" "\\" backslash)
  if(NOT quote EQUAL -1 OR NOT backslash EQUAL -1)
    message(FATAL_ERROR "stage_embed_binary: ${file}: a path with a quote or a backslash cannot go into .incbin")
  endif()
  set(out ${CMAKE_CURRENT_BINARY_DIR}/embedded_${var}.cc)
  file(WRITE ${out}.in
       "// Generated by stage_embed_binary (cmake/StageTarget.cmake) from ${file}. Do not edit.\n"
       "__asm__(\".section .rodata\\n.global ${var}\\n.global ${var}_end\\n.balign 16\\n${var}:\\n"
       ".incbin \\\"${file}\\\"\\n${var}_end:\\n.previous\\n\");\n")
  configure_file(${out}.in ${out} COPYONLY)
  set_source_files_properties(${out} PROPERTIES OBJECT_DEPENDS ${file})
  target_sources(${target} PRIVATE ${out})
endfunction()
