#!/usr/bin/env bash
# Seed corpora for the fuzz targets, from the project's own fixtures and a small sim recording
# (made here, so the seeds stay small: libFuzzer mutates whole inputs).
set -euo pipefail
cd "$(dirname "$0")/.."
corpus=fuzz/corpus
mkdir -p $corpus/mcap $corpus/cdr $corpus/files $corpus/prepare $corpus/rosbag2
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
# rosbag2: a small sqlite3 bag and its metadata.yaml written by rosbags (leading byte 0: database,
# 1: metadata).
.venv/bin/python - "$corpus/rosbag2" <<'PY'
import pathlib, sys, tempfile
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
store = get_typestore(Stores.ROS2_HUMBLE)
String = store.types["std_msgs/msg/String"]
out = pathlib.Path(sys.argv[1])
with tempfile.TemporaryDirectory() as tmp:
    bag = pathlib.Path(tmp) / "bag"
    with Writer(bag, version=8, storage_plugin=StoragePlugin.SQLITE3) as writer:
        connection = writer.add_connection("/chatter", String.__msgtype__, typestore=store)
        for i in range(3):
            writer.write(connection, i, store.serialize_cdr(String(data=f"m{i}"), String.__msgtype__))
    (out / "small.db3").write_bytes(b"\x00" + (bag / "bag.db3").read_bytes())
    (out / "metadata.yaml").write_bytes(b"\x01" + (bag / "metadata.yaml").read_bytes())
PY
