find_package(Eigen3 3.3 NO_MODULE QUIET)
if(NOT TARGET Eigen3::Eigen)
  message(FATAL_ERROR "Eigen 3.3+ not found. On Debian/Ubuntu: apt-get install libeigen3-dev")
endif()
