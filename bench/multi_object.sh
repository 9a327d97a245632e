#!/usr/bin/env bash
# The multi-object benchmark's recordings (issue 34): sim scenes with two subjects whose paths
# overlap in the image, one of them leaving the view and coming back, from fixed seeds. Three sets
# of the same six scenarios with different seeds: `tune` (settings are chosen on it), `holdout`
# and `final` (measured, nothing chosen on them). Then the candidate detection measured on the set
# (bench/detection.rs), and the tracking: `gdvae-node evaluate` with config/objects.toml (MOTA,
# IDF1, ID switches, returns that got their id back, per-track heading).
#
#   bench/multi_object.sh SET [OUT_DIR]
#
# Recordings go to OUT_DIR/SET/ (default /work/data/bench-multi, or $BENCH_DIR) and are made once.
set -euo pipefail
cd "$(dirname "$0")/.."

SET=${1:?usage: bench/multi_object.sh tune|holdout|final [OUT_DIR]}
OUT=${2:-${BENCH_DIR:-/work/data/bench-multi}}
case $SET in
  tune) BASE=600 ;;
  holdout) BASE=700 ;;
  final) BASE=800 ;;
  *) echo "bench/multi_object.sh: unknown set '$SET' (tune, holdout or final)" >&2; exit 2 ;;
esac
SIM=./target/release/sim
[[ -x $SIM ]] || { echo "bench/multi_object.sh: $SIM missing: run 'make sim' first" >&2; exit 2; }

# name | primary's family | the other's | motion | away interval of the other (s)
SCENARIOS=(
  "walk-qb|quadruped|biped|walk|4-6"
  "walk-bq|biped|quadruped|walk|6-9"
  "walk-qq|quadruped|quadruped|walk|4-6"
  "walk-bb|biped|biped|walk|5-8"
  "idle-qb|quadruped|biped|idle|3-5"
  "idle-bb|biped|biped|idle|4-7"
)
mkdir -p "$OUT/$SET"
index=0
for scenario in "${SCENARIOS[@]}"; do
  IFS='|' read -r name primary other motion away <<< "$scenario"
  file=$OUT/$SET/$name.mcap
  if [[ ! -f $file ]]; then
    $SIM record --out "$file" --families "$primary" --others "$other" --motion "$motion" \
      --away "1:$away" --duration 12 --decimation 2 --seed $((BASE + index)) >&2
  fi
  index=$((index + 1))
done
cargo run --release --quiet --example detection -- "$OUT/$SET"/*.mcap
echo "command: ./target/release/gdvae-node evaluate $OUT/$SET/*.mcap --config config/objects.toml"
./target/release/gdvae-node evaluate "$OUT/$SET"/*.mcap --config config/objects.toml
