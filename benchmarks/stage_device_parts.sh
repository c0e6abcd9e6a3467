#!/usr/bin/env bash
# After the warp wheel was staged in three parts (.wp1 .wp2 .wp3: warp.part.*, with warp.name,
# warp.sha256 and the small wheels in .wp3): re-split it into four ~38 MB parts
# (.wpa .wpb .wpc .wpd, git-ignored; the small wheels and the wheel's name go with .wpd), so that
# each part plus the tracked tree (about 17 MB) stays under a device call's 64 MiB.
# Then, back to back with nothing else in the same batch (the machine goes back 30 s after a call):
#   run carry [".wpa"]: mkdir -p /root/stash && cp .wpa/* /root/stash/
#   run carry [".wpb"], then [".wpc"]: cp .wpN/* /root/stash/
#   run carry [".wpd"]: cp .wpd/* /root/stash/ && source benchmarks/gpu_setup.sh && ...
set -eu
[ -f .wp3/warp.name ] || { echo "stage the warp wheel into .wp1 .wp2 .wp3 first" >&2; exit 2; }
name=$(cat .wp3/warp.name)
rm -rf .wpa .wpb .wpc .wpd .wpjoin && mkdir -p .wpa .wpb .wpc .wpd .wpjoin
for d in /.wpa/ /.wpb/ /.wpc/ /.wpd/ /.wpjoin/; do
  grep -qxF "$d" .git/info/exclude || echo "$d" >> .git/info/exclude
done
cat .wp1/warp.part.* .wp2/warp.part.* .wp3/warp.part.* > ".wpjoin/$name"
echo "$(cat .wp3/warp.sha256)  .wpjoin/$name" | sha256sum -c --quiet
split -b 38m -d ".wpjoin/$name" .wpjoin/warp.part.
mv .wpjoin/warp.part.00 .wpa/; mv .wpjoin/warp.part.01 .wpb/
mv .wpjoin/warp.part.02 .wpc/; mv .wpjoin/warp.part.03 .wpd/
[ ! -e .wpjoin/warp.part.04 ] || { echo "the wheel needs a fifth part" >&2; exit 1; }
cp .wp3/*.whl .wp3/warp.name .wpd/
rm -rf .wpjoin
du -sh .wpa .wpb .wpc .wpd
