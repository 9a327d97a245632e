#!/usr/bin/env bash
# The multi-object benchmark's recordings (issue 34): sim scenes with two subjects whose paths
# overlap in the image, one of them leaving the view and coming back, from fixed seeds. Three sets
# of the same six scenarios with different seeds: `tune` (settings are chosen on it), `holdout`
# and `final` (measured, nothing chosen on them); `returns`: fourteen 20 s scenes in which the other
# subject leaves twice for 3-5 s, to count re-identifications (`returns-tune`: the same scenes from
# other seeds, for tuning; `tune2`: a second tuning set of the six scenarios). Then the candidate detection measured on the set
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
DURATION=12
case $SET in
  tune) BASE=600 ;;
  tune2) BASE=650 ;;
  holdout) BASE=700 ;;
  final) BASE=800 ;;
  returns) BASE=900 DURATION=20 ;;
  returns-tune) BASE=950 DURATION=20 ;;
  *) echo "bench/multi_object.sh: unknown set '$SET' (tune, tune2, holdout, final, returns or returns-tune)" >&2; exit 2 ;;
esac
SIM=./target/release/sim
[[ -x $SIM ]] || { echo "bench/multi_object.sh: $SIM missing: run 'make sim' first" >&2; exit 2; }

# name | primary's family | the other's | motion | away intervals of the other (s)
SCENARIOS=(
  "walk-qb|quadruped|biped|walk|4-6"
  "walk-bq|biped|quadruped|walk|6-9"
  "walk-qq|quadruped|quadruped|walk|4-6"
  "walk-bb|biped|biped|walk|5-8"
  "idle-qb|quadruped|biped|idle|3-5"
  "idle-bb|biped|biped|idle|4-7"
)
if [[ $SET == returns || $SET == returns-tune ]]; then
  # Re-identification (nothing is chosen on it): the other subject leaves twice for 3-5 s; ten
  # scenes pair the families (20 returns beside the other family), four pair one family (8).
  SCENARIOS=()
  for k in 0 1 2 3 4; do
    SCENARIOS+=("walk-qb$k|quadruped|biped|walk|3-$((6 + k % 3)),1:11-$((14 + k % 3))")
    SCENARIOS+=("walk-bq$k|biped|quadruped|walk|3-$((6 + k % 3)),1:11-$((14 + k % 3))")
  done
  for k in 0 1; do
    SCENARIOS+=("walk-qq$k|quadruped|quadruped|walk|3-7,1:11-15")
    SCENARIOS+=("walk-bb$k|biped|biped|walk|3-7,1:11-15")
  done
fi
mkdir -p "$OUT/$SET"
index=0
for scenario in "${SCENARIOS[@]}"; do
  IFS='|' read -r name primary other motion away <<< "$scenario"
  file=$OUT/$SET/$name.mcap
  if [[ ! -f $file ]]; then
    $SIM record --out "$file" --families "$primary" --others "$other" --motion "$motion" \
      --away "1:$away" --duration $DURATION --decimation 2 --seed $((BASE + index)) >&2
  fi
  index=$((index + 1))
done
cargo run --release --quiet --example detection -- "$OUT/$SET"/*.mcap
echo "command: ./target/release/gdvae-node evaluate $OUT/$SET/*.mcap --config config/objects.toml"
./target/release/gdvae-node evaluate "$OUT/$SET"/*.mcap --config config/objects.toml
