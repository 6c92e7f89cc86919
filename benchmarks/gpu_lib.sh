# Helpers shared by the scripts run on a lent GPU machine (gpu_session.sh, gpu_recipe_sweep.sh).
# Source it; it defines functions only.

# abs_dir DIR: creates DIR and prints its absolute path (the scripts cd to the repository root).
abs_dir() { mkdir -p "$1" && (cd "$1" && pwd); }

# machine_info PY: date, GPU, Python / JAX / MuJoCo versions, cores and commit, one per line.
machine_info() {
  date -u +%Y-%m-%dT%H:%M:%SZ
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>&1
  "$1" -c "import sys, jax, mujoco; print(sys.version.split()[0], 'jax', jax.__version__, 'mujoco', mujoco.__version__, jax.devices())" 2>&1 | grep -v warp
  nproc
  git -C "$(dirname "${BASH_SOURCE[0]}")" rev-parse --short HEAD 2>/dev/null
}

# latest_step RUN_DIR: the newest checkpoint step of a run, or nothing.
latest_step() {
  ls "$1/checkpoints" 2>/dev/null | grep -E '^[0-9]+$' | sort -n | tail -n 1
}

# stage_bundle DIR: keeps the first part of a gpu_bundle.sh bundle (DIR/a) in /tmp/bundle, where
# it outlasts the call that copied it, for install_bundle in the next call on the same machine.
stage_bundle() {
  mkdir -p /tmp/bundle && cp "$1"/a/* /tmp/bundle/ && ls -la /tmp/bundle
}

# install_bundle DIR: with DIR/b here and DIR/a staged, rebuilds warp.so, installs the bundle's
# wheels and files into /tmp/site and puts it on PYTHONPATH (returns 1 if a part is missing).
install_bundle() {
  local site=/tmp/site
  ls /tmp/bundle/warp_so.xz.00 "$1"/b/warp_so.xz.01 > /dev/null || return 1
  mkdir -p "$site" && tar -xJf "$1/b/site.tar.xz" -C "$site" || return 1
  cat /tmp/bundle/warp_so.xz.* "$1"/b/warp_so.xz.* | xz -d -T0 > "$site/warp/bin/warp.so" || return 1
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target "$site" "$1"/b/*.whl || return 1
  export PYTHONPATH="$site${PYTHONPATH:+:$PYTHONPATH}"
  python3 -c "import warp, mujoco; from mujoco import mjx; print('warp', warp.config.version, 'mujoco', mujoco.__version__)"
}
