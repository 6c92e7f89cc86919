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
