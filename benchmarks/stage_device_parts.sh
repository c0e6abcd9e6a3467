#!/usr/bin/env bash
# Packs what a GPU machine without a package index needs into parts that each fit one device
# call beside the tracked tree (64 MiB a call): the warp wheel staged by
# ../shared/tools/stage-device-wheels.sh (.wp1 .wp2 .wp3, with the small wheels in .wp3), Ray
# with the dependencies that machine lacks, and any FOLDERs given (a scene suite, say), which
# land under /root/stash/data/NAME there. One tar, split into parts .dv1 .dv2 ... (git-ignored)
# each as large as the working tree leaves of a call's 64 MiB.
#   bash benchmarks/stage_device_parts.sh [--no-ray] [--genesis] [--taichi] [FOLDER ...]
# (--no-ray: leave Ray out, one part less, for work that runs --part processes itself;
#  --taichi: add the taichi wheel at the version installed here and the small pure-Python
#  packages it imports, about 55 MB, for taichi-mpm there;
#  --genesis: add genesis-world and what it imports that the machine lacks, about 560 MB, for
#  `mosiv bench sim --peer genesis` there; benchmarks/genesis_wheels.py lists them, at the
#  versions installed here, so run this where mosiv-genesis[engine] is installed; the GL
#  libraries it loads come as Debian packages through apt-get download)
# Then, back to back with nothing else in the same batch (the machine goes back 30 s after a
# call), one call per part, each carrying its part:
#   mkdir -p /root/stash && cp .dvN/* /root/stash/
# and in the last call (or any later one): source benchmarks/gpu_setup.sh && ...
set -eu
with_ray=1
with_genesis=0
with_taichi=0
while [ $# -gt 0 ]; do
  case "$1" in
  --no-ray) with_ray=0 ;;
  --genesis) with_genesis=1 ;;
  --taichi) with_taichi=1 ;;
  *) break ;;
  esac
  shift
done
[ -f .wp3/warp.name ] || { echo "stage the warp wheel into .wp1 .wp2 .wp3 first" >&2; exit 2; }
pack=.dvpack
rm -rf "$pack" .dv[0-9]* && mkdir -p "$pack/wheels" "$pack/data"
grep -qxF "/.dv*" .git/info/exclude || echo "/.dv*" >> .git/info/exclude
name=$(cat .wp3/warp.name)
cat .wp1/warp.part.* .wp2/warp.part.* .wp3/warp.part.* > "$pack/wheels/$name"
echo "$(cat .wp3/warp.sha256)  $pack/wheels/$name" | sha256sum -c --quiet
cp .wp3/*.whl "$pack/wheels/"
# Ray and what it needs beyond the GPU image's packages (jsonschema and its own)
[ "$with_ray" = 1 ] && python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
  -d "$pack/wheels" "ray>=2.9" jsonschema jsonschema-specifications referencing rpds-py
if [ "$with_taichi" = 1 ]; then
  taichi_version=$(python3 -c "import importlib.metadata as m; print(m.version('taichi'))")
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    -d "$pack/wheels" "taichi==$taichi_version" dill colorama rich pygments markdown-it-py mdurl
fi
if [ "$with_genesis" = 1 ]; then
  python3 benchmarks/genesis_wheels.py --skip-present "$pack/wheels" > "$pack/genesis.txt"
  while read -r requirement; do
    python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
      --implementation cp --platform manylinux_2_35_x86_64 --platform manylinux_2_34_x86_64 \
      --platform manylinux_2_31_x86_64 --platform manylinux_2_28_x86_64 \
      --platform manylinux_2_27_x86_64 --platform manylinux_2_24_x86_64 \
      --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
      --platform manylinux_2_12_x86_64 --platform manylinux2010_x86_64 \
      --platform manylinux_2_5_x86_64 --platform manylinux1_x86_64 \
      -d "$pack/wheels" "$requirement" 2>/dev/null && continue
    # no wheel on the index (an sdist only): build one here, which serves Python 3.12 only
    # when the package is pure Python
    python3 -m pip wheel -q --no-deps -w "$pack/built" "$requirement"
    for wheel in "$pack"/built/*.whl; do
      case "$wheel" in
      *-py3-none-any.whl | *-py2.py3-none-any.whl) mv "$wheel" "$pack/wheels/" ;;
      *) echo "$requirement: no wheel for Python 3.12 on the index and not pure Python" >&2; exit 2 ;;
      esac
    done
  done < "$pack/genesis.txt"
  rm -rf "$pack/built" "$pack/genesis.txt"
  # genesis imports pygel3d, which loads the system's libGL.so.1: the GPU image has none, so the
  # GL dispatch libraries travel as Debian packages that gpu_setup.sh unpacks there
  mkdir -p "$pack/data/debs" /tmp/amd64/partial
  apt_options='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
  # shellcheck disable=SC2086
  apt-get $apt_options update > /dev/null
  # shellcheck disable=SC2086
  (cd "$pack/data/debs" && apt-get $apt_options download libgl1 libglx0 libglvnd0 libegl1 libopengl0 > /dev/null)
fi
for folder in "$@"; do
  cp -r "$folder" "$pack/data/$(basename "$folder")"
done
# a call carries the working tree (tracked and untracked-not-ignored files) beside its part:
# the parts are as large as what the tree leaves of 64 MiB, less 2 MiB of headroom. The tree
# is counted as the disk space its files take (whole blocks, what du says): counted by bytes,
# a 13.5 MB tree beside a 50 MiB part looked like room to spare and the call was refused.
tree_kib=$(git ls-files -z --cached --others --exclude-standard | du -c -k --files0-from=- | tail -1 | cut -f1)
case "$tree_kib" in
'' | *[!0-9]*)
  echo "could not measure the working tree (git ls-files | du --files0-from, GNU du)" >&2
  exit 1
  ;;
esac
part_bytes=$((64 * 1048576 - tree_kib * 1024 - 2 * 1048576))
if [ "$part_bytes" -lt $((8 * 1048576)) ]; then
  echo "the working tree takes $((tree_kib / 1024)) MiB of a call's 64 MiB: too little is left for a part" >&2
  exit 1
fi
echo "working tree $((tree_kib / 1024)) MiB: parts of $((part_bytes / 1048576)) MiB"
tar -cf - -C "$pack" wheels data | split -b "$part_bytes" -d - "$pack/bundle.part."
n=0
for part in "$pack"/bundle.part.*; do
  n=$((n + 1))
  mkdir -p ".dv$n" && mv "$part" ".dv$n/"
done
rm -rf "$pack"
du -sh .dv[0-9]*
