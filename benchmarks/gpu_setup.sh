#!/usr/bin/env bash
# On the GPU machine (Python 3.12, CUDA torch, no package index): install the staged wheels
# (warp, Ray, taichi and Genesis where staged) and this checkout, offline.
# The wheels travel in the parts that benchmarks/stage_device_parts.sh makes (one device call
# each, copied into /root/stash); the folders packed with them land in /root/stash/data.
# Usage: source benchmarks/gpu_setup.sh   (repository root; taichi comes staged with
# `stage_device_parts.sh --taichi`, or carried as .ti with .tideps, the small pure-Python
# packages it needs: dill colorama rich pygments markdown-it-py mdurl)
set -e
# When the checkout plus .ti no longer fits one call (64 MiB), split the taichi wheel like warp's:
#   split -b 30M .ti/taichi-*.whl .tia/ti.part. ; move ti.part.ab and the small wheels to .tib;
#   basename of the wheel > .tib/ti.name; carry .tia, then .tib, copying each into /root/stash.
if [ ! -d /root/site/warp ]; then
  (cd /root/stash && cat bundle.part.* | tar -xf - && mv wheels/*.whl .)
  if [ -f /root/stash/ti.name ]; then
    (cd /root/stash && cat ti.part.* > "$(cat ti.name)")
  fi
  python3 -m pip install -q --no-index --no-deps --target /root/site /root/stash/*.whl \
    $(ls .ti/*.whl 2>/dev/null)
fi
# GL libraries staged for Genesis (stage_device_parts.sh --genesis), unpacked into / once
if ls /root/stash/data/debs/*.deb > /dev/null 2>&1 && ! ldconfig -p | grep -q libGL.so.1; then
  for deb in /root/stash/data/debs/*.deb; do dpkg -x "$deb" /; done
  ldconfig
fi
# no display there: pyglet (imported by Genesis's viewer) must not look for an X server
export PYGLET_HEADLESS=1
export PYTHONPATH=/root/site:$PWD/.tideps:$PWD:$PWD/plugins/mosiv-warp-mpm:$PWD/plugins/mosiv-taichi-mpm:$PWD/plugins/mosiv-gauss:$PWD/plugins/mosiv-lift:$PWD/plugins/mosiv-synth:$PWD/plugins/mosiv-genesis:$PWD/plugins/mosiv-nerf
for d in . plugins/mosiv-warp-mpm plugins/mosiv-taichi-mpm plugins/mosiv-gauss plugins/mosiv-lift plugins/mosiv-synth plugins/mosiv-genesis plugins/mosiv-nerf; do
  python3 -m pip install -q --no-deps --no-build-isolation --no-index -e "$d" >/dev/null 2>&1 || true
done
export PATH=$PATH:/root/.local/bin
set +e
