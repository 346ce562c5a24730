# TetGen 1.5 (Debian libtet1.5-dev) ships no CMake config. TETLIBRARY must be defined so the
# header declares tetrahedralize() and errors throw an int instead of calling exit().
find_path(TETGEN_INCLUDE_DIR tetgen.h)
find_library(TETGEN_LIBRARY tet)
if(NOT TETGEN_INCLUDE_DIR OR NOT TETGEN_LIBRARY)
  message(FATAL_ERROR "TetGen not found. On Debian/Ubuntu: apt-get install libtet1.5-dev")
endif()
add_library(matlearn_tetgen INTERFACE)
add_library(matlearn::tetgen ALIAS matlearn_tetgen)
target_include_directories(matlearn_tetgen INTERFACE ${TETGEN_INCLUDE_DIR})
target_link_libraries(matlearn_tetgen INTERFACE ${TETGEN_LIBRARY})
target_compile_definitions(matlearn_tetgen INTERFACE TETLIBRARY)
