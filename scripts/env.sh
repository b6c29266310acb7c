# Sourced by the project's scripts: where the virtual environment and the
# colcon build live, and the environment every process here runs with.
# shellcheck shell=bash
VFD_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# The venv and the colcon workspace live outside the source tree: CMake refuses
# exported include paths that point into the package's own source directory.
# The venv is keyed by requirements.txt (checkouts with the same pins share it),
# the build by the checkout's path.
VFD_CACHE="${VFD_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/vfd_ros2}"
VFD_VENV="${VFD_VENV:-$VFD_CACHE/venv-$(sha256sum "$VFD_ROOT/requirements.txt" | cut -c1-12)}"
VFD_WORK="${VFD_WORK:-$VFD_CACHE/ws-$(printf '%s' "$VFD_ROOT" | sha256sum | cut -c1-12)}"
VFD_INSTALL="$VFD_WORK/install"
VFD_PYVER="$("${VFD_VENV}/bin/python" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")' 2>/dev/null || echo 3.11)"

# DDS discovery stays on this machine: no multicast onto the network.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-42}"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"

vfd_activate() {
  export VIRTUAL_ENV="$VFD_VENV"
  export PATH="$VFD_VENV/bin:$VFD_INSTALL/lib/vfd_ros2:$PATH"
  export PYTHONPATH="$VFD_INSTALL/lib/python$VFD_PYVER/site-packages${PYTHONPATH:+:$PYTHONPATH}"
  export AMENT_PREFIX_PATH="$VFD_INSTALL:$VFD_VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
  export LD_LIBRARY_PATH="$VFD_INSTALL/lib:$VFD_VENV/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
  export PYTHONDONTWRITEBYTECODE=1
}

# A DDS domain of this process tree's own (tests, benchmarks): two runs on one
# machine must never see each other's nodes. The lock is held by a file
# descriptor that the exec'd program inherits, until it exits.
vfd_private_domain() {
  local lock_dir="${TMPDIR:-/tmp}/vfd_ros2_domains" domain
  mkdir -p "$lock_dir"
  for domain in $(seq 100 199); do
    exec {VFD_DOMAIN_LOCK}>"$lock_dir/$domain.lock"
    if flock -n "$VFD_DOMAIN_LOCK"; then
      export ROS_DOMAIN_ID="$domain"
      return 0
    fi
    exec {VFD_DOMAIN_LOCK}>&-
  done
  echo "no free ROS_DOMAIN_ID in 100..199 (every one is held by a run)" >&2
  return 1
}
