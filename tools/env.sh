# Source me: puts the project's .venv and the colcon install/ on this shell's paths.
#   source tools/env.sh
_sonar_ring_root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
_sonar_ring_venv=$(readlink -f "$_sonar_ring_root/.venv")
export VIRTUAL_ENV=$_sonar_ring_venv
export PATH=$_sonar_ring_venv/bin:$PATH
export AMENT_PREFIX_PATH=$_sonar_ring_venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}
export CMAKE_PREFIX_PATH=$_sonar_ring_venv${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}
# shellcheck disable=SC1091
source "$_sonar_ring_root/install/local_setup.bash"
unset _sonar_ring_root _sonar_ring_venv
