# Included last by every interface package in msg_defs/.
# Work-around for the PyPI ROS wheels: their exported CMake targets carry include
# directories of the machine they were built on (e.g. /opt/python/cp311-cp311/include/...),
# which do not exist here and make CMake refuse to generate. Drop every absolute include
# directory that does not exist from all imported targets. Run last, so that targets
# imported inside rosidl_generate_interfaces() are covered too (include directories are
# only evaluated at generate time).
get_property(_imported DIRECTORY PROPERTY IMPORTED_TARGETS)
foreach(_t IN LISTS _imported)
  get_target_property(_dirs ${_t} INTERFACE_INCLUDE_DIRECTORIES)
  if(NOT _dirs)
    continue()
  endif()
  set(_keep "")
  set(_changed FALSE)
  foreach(_d IN LISTS _dirs)
    if(IS_ABSOLUTE "${_d}" AND NOT EXISTS "${_d}")
      set(_changed TRUE)
    else()
      list(APPEND _keep "${_d}")
    endif()
  endforeach()
  if(_changed)
    set_target_properties(${_t} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_keep}")
  endif()
endforeach()
