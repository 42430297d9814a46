#!/usr/bin/env bash
# Wheels the device machine needs for bench/gpu_session.sh (it has torch but no gsplat, and no network), written to
# .whl/ (ignored by git). gsplat's wheel carries GLM's HTML manual and test suite (5.7 MB of its 6.5 MB); they are
# dropped so that the wheels fit beside the working tree in the 64 MiB a device call may carry.
set -eu
dest=${1:-.whl}
mkdir -p "$dest"
tmp=$(mktemp -d)
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux2014_x86_64 -d "$tmp" gsplat==1.5.3 plyfile==1.1.5
cp "$tmp"/plyfile-*.whl "$dest"/
( cd "$tmp" && mkdir unpacked && cd unpacked && unzip -q ../gsplat-1.5.3-py3-none-any.whl \
  && rm -rf gsplat/cuda/csrc/third_party/glm/doc gsplat/cuda/csrc/third_party/glm/test \
  && python3 -c "
import csv, os
path = 'gsplat-1.5.3.dist-info/RECORD'
rows = [row for row in csv.reader(open(path)) if os.path.exists(row[0])]
csv.writer(open(path, 'w', newline='')).writerows(rows)" \
  && zip -q -r -9 "$tmp/gsplat-trimmed.whl" gsplat gsplat-1.5.3.dist-info )
cp "$tmp/gsplat-trimmed.whl" "$dest/gsplat-1.5.3-py3-none-any.whl"
rm -rf "$tmp"
ls -la "$dest"
