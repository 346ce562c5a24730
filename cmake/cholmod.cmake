# CHOLMOD: SuiteSparse >= 7 ships a CMake config; Debian 12's 5.12 ships neither config nor
# pkg-config, so fall back to locating the header and libraries by hand.
find_package(CHOLMOD CONFIG QUIET)
add_library(matlearn_cholmod INTERFACE)
add_library(matlearn::cholmod ALIAS matlearn_cholmod)
if(TARGET SuiteSparse::CHOLMOD)
  target_link_libraries(matlearn_cholmod INTERFACE SuiteSparse::CHOLMOD)
else()
  find_path(CHOLMOD_INCLUDE_DIR cholmod.h PATH_SUFFIXES suitesparse)
  find_library(CHOLMOD_LIBRARY cholmod)
  find_library(SUITESPARSECONFIG_LIBRARY suitesparseconfig)
  if(NOT CHOLMOD_INCLUDE_DIR OR NOT CHOLMOD_LIBRARY OR NOT SUITESPARSECONFIG_LIBRARY)
    message(FATAL_ERROR "CHOLMOD (SuiteSparse) not found. On Debian/Ubuntu: "
                        "apt-get install libsuitesparse-dev libopenblas0-pthread")
  endif()
  target_include_directories(matlearn_cholmod INTERFACE ${CHOLMOD_INCLUDE_DIR})
  target_link_libraries(matlearn_cholmod INTERFACE ${CHOLMOD_LIBRARY} ${SUITESPARSECONFIG_LIBRARY})
endif()
