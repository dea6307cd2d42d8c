#!/usr/bin/env bash
# Set up everything sonar_ring needs on a fresh machine, idempotently:
#   1. .venv with the pinned ROS 2 Kilted wheels and dev tools (requirements.txt);
#      the environment itself lives outside the repository (CMake refuses
#      exported include paths inside the source tree, and numpy's headers are
#      in it), keyed by the lock file's hash, and .venv links to it;
#   2. the wheels' CMake exports pointed at this machine's Python and numpy
#      headers (they name the build host's /opt/python/cp311-cp311);
#   3. colcon build of the package (messages + Python package) into install/.
# A second run reinstalls nothing and only rebuilds what changed.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD
wanted=$(sha256sum requirements.txt | cut -d' ' -f1)
venv=${SONAR_RING_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/sonar_ring/venv-${wanted:0:16}}

if [ ! -f "$venv/.complete" ]; then
  echo "bootstrap: installing pinned packages into $venv"
  rm -rf "$venv"
  "${PYTHON:-python3}" -m venv "$venv"
  "$venv/bin/pip" install --quiet --disable-pip-version-check -r requirements.txt
  touch "$venv/.complete"
fi
ln -sfn "$venv" .venv

py_include=$("$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
np_include=$("$venv/bin/python" -c 'import numpy; print(numpy.get_include())')
{ grep -rlZ --include='*.cmake' '/opt/python/cp311-cp311' "$venv/share" || true; } \
  | xargs -0 -r sed -i \
      -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$np_include#g" \
      -e "s#/opt/python/cp311-cp311/include/python3.11#$py_include#g"

mkdir -p log
export CMAKE_PREFIX_PATH=$venv AMENT_PREFIX_PATH=$venv
export PATH=$venv/bin:$PATH VIRTUAL_ENV=$venv
colcon --log-base log build --base-paths "$root" --build-base build --install-base install \
  --event-handlers console_cohesion- summary- status- \
  --cmake-args -DPython3_EXECUTABLE="$venv/bin/python" -DBUILD_TESTING=OFF -Wno-dev \
  > "$root/log/colcon-build.txt" 2>&1 || { cat log/colcon-build.txt; echo "bootstrap: colcon build failed"; exit 1; }
# numba compiles the core's kernels at their first use and caches the machine code
# beside the installed modules: do it here (about 1.5 minutes after a change), not in the
# first test or the first ping.  An unchanged build keeps the cache.
(set +u && source "$root/tools/env.sh" && cd / && python -c \
  "from sonar_ring import confidence, echoes, explain, image_method, localise, mapping, pipeline, ring_consistency
for module in (echoes, localise, confidence, ring_consistency, pipeline, mapping, image_method, explain):
    module.load_kernels()") \
  || { echo "bootstrap: loading the compiled kernels failed"; exit 1; }
echo "bootstrap: built into install/ (source tools/env.sh to use it)"
