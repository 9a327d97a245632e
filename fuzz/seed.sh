#!/usr/bin/env bash
# Seed corpora for the fuzz targets, from the project's own fixtures and a small sim recording
# (made here, so the seeds stay small: libFuzzer mutates whole inputs).
set -euo pipefail
cd "$(dirname "$0")/.."
corpus=fuzz/corpus
mkdir -p $corpus/mcap $corpus/cdr $corpus/files $corpus/prepare
small=$corpus/mcap/small.mcap
if [[ ! -s $small ]]; then
  ./target/release/sim record --out $small --duration 0.1 --decimation 16 --ground-extent 0.5 \
    --depth-images --no-compression --seed 1 >/dev/null
  ./target/release/sim record --out $corpus/mcap/small-zstd.mcap --duration 0.1 --decimation 16 \
    --ground-extent 0.5 --seed 2 >/dev/null
fi
# Each message of the small recording is a CDR seed (PointCloud2, Image, CameraInfo).
.venv/bin/python - "$small" "$corpus/cdr" <<'PY'
import sys
from mcap.reader import make_reader
with open(sys.argv[1], "rb") as f:
    for i, (_, channel, message) in enumerate(make_reader(f).iter_messages()):
        if channel.message_encoding == "cdr":
            open(f"{sys.argv[2]}/{channel.topic.strip('/').replace('/', '_')}-{i}", "wb").write(message.data)
PY
# Files: a leading byte picks the reader (0 PLY, 1 PCD, 2 OBJ, 3 XYZ).
for f in tests/fixtures/* sim/samples/meshes/quadruped_rest.ply; do
  case $f in
    *.ply) k='\x00' ;; *.pcd) k='\x01' ;; *.obj) k='\x02' ;; *.xyz|*.csv) k='\x03' ;; *) continue ;;
  esac
  { printf "$k"; head -c 65536 "$f"; } > "$corpus/files/$(basename "$f")"
done
printf '\x03x y z\n0 0 0\n1 2 3\n' > $corpus/files/tiny.xyz
head -c 4096 /dev/urandom > $corpus/prepare/random
