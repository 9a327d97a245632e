#!/usr/bin/env bash
# The multi-object benchmark's recordings (issue 34): sim scenes with two subjects whose paths
# overlap in the image, one of them leaving the view and coming back, from fixed seeds. Three sets
# of the same six scenarios with different seeds: `tune` (settings are chosen on it), `holdout`
# and `final` (measured, nothing chosen on them); `returns`: fourteen 20 s scenes in which the other
# subject leaves twice for 3-5 s, to count re-identifications (`returns-tune`: the same scenes from
# other seeds, for tuning; `tune2`: a second tuning set of the six scenarios); `cross`: eight 12 s
# scenes in which the other subject walks back and forth across the view (`--others-motion cross`)
# in front of the primary or behind it, so that their paths cross in the image twice a scene and
# one hides the other (`cross-tune`, `cross-tune2`: the same scenes from other seeds, for tuning);
# `three`: four 12 s scenes with three subjects (two walking beside the primary, or one crossing in
# front of it and one behind; nothing is chosen on it). Then the
# candidate detection measured on the set
# (bench/detection.rs), and the tracking: `gdvae-node evaluate` with config/objects.toml (MOTA,
# IDF1, ID switches, returns that got their id back, per-track heading).
#
#   bench/multi_object.sh SET [OUT_DIR]
#
# Recordings go to OUT_DIR/SET/ (default /work/data/bench-multi, or $BENCH_DIR) and are made once.
set -euo pipefail
cd "$(dirname "$0")/.."

SET=${1:?usage: bench/multi_object.sh tune|tune2|holdout|final|returns|returns-tune|cross|cross-tune|cross-tune2|three [OUT_DIR]}
OUT=${2:-${BENCH_DIR:-/work/data/bench-multi}}
DURATION=12
case $SET in
  tune) BASE=600 ;;
  tune2) BASE=650 ;;
  holdout) BASE=700 ;;
  final) BASE=800 ;;
  returns) BASE=900 DURATION=20 ;;
  returns-tune) BASE=950 DURATION=20 ;;
  cross-tune) BASE=1000 ;;
  cross-tune2) BASE=1060 ;;
  cross) BASE=1100 ;;
  three) BASE=1200 ;;
  *) echo "bench/multi_object.sh: unknown set '$SET' (tune, tune2, holdout, final, returns, returns-tune, cross, cross-tune, cross-tune2 or three)" >&2; exit 2 ;;
esac
SIM=./target/release/sim
[[ -x $SIM ]] || { echo "bench/multi_object.sh: $SIM missing: run 'make sim' first" >&2; exit 2; }

# name | primary's family | the other's | motion | away intervals of the other (s) | the other's
# motion and stage (empty: as the primary, beside it)
SCENARIOS=(
  "walk-qb|quadruped|biped|walk|4-6|"
  "walk-bq|biped|quadruped|walk|6-9|"
  "walk-qq|quadruped|quadruped|walk|4-6|"
  "walk-bb|biped|biped|walk|5-8|"
  "idle-qb|quadruped|biped|idle|3-5|"
  "idle-bb|biped|biped|idle|4-7|"
)
if [[ $SET == returns || $SET == returns-tune ]]; then
  # Re-identification (nothing is chosen on it): the other subject leaves twice for 3-5 s; ten
  # scenes pair the families (20 returns beside the other family), four pair one family (8).
  SCENARIOS=()
  for k in 0 1 2 3 4; do
    SCENARIOS+=("walk-qb$k|quadruped|biped|walk|3-$((6 + k % 3)),1:11-$((14 + k % 3))|")
    SCENARIOS+=("walk-bq$k|biped|quadruped|walk|3-$((6 + k % 3)),1:11-$((14 + k % 3))|")
  done
  for k in 0 1; do
    SCENARIOS+=("walk-qq$k|quadruped|quadruped|walk|3-7,1:11-15|")
    SCENARIOS+=("walk-bb$k|biped|biped|walk|3-7,1:11-15|")
  done
fi
if [[ $SET == cross* ]]; then
  # Crossing paths: the other subject crosses the view 1 m in front of the primary's stage
  # (2.2 m from the camera) or 0.9 m behind it (4.1 m), there and back in 12 s; it stays.
  FRONT="cross 1.0:0" BEHIND="cross -0.9:0"
  SCENARIOS=(
    "front-qb|quadruped|biped|walk||$FRONT"
    "behind-bq|biped|quadruped|walk||$BEHIND"
    "front-bb|biped|biped|walk||$FRONT"
    "behind-qq|quadruped|quadruped|walk||$BEHIND"
    "front-bq-idle|biped|quadruped|idle||$FRONT"
    "behind-qb-idle|quadruped|biped|idle||$BEHIND"
    "front-qq|quadruped|quadruped|walk||$FRONT"
    "behind-bb|biped|biped|walk||$BEHIND"
  )
fi
if [[ $SET == three ]]; then
  SCENARIOS=(
    "walk-qbq|quadruped|biped,quadruped|walk||"
    "walk-bqb|biped|quadruped,biped|walk||"
    "cross-qbq|quadruped|biped,quadruped|walk||cross 1.0:0,-0.9:0"
    "cross-bqb|biped|quadruped,biped|walk||cross 1.0:0,-0.9:0"
  )
fi
mkdir -p "$OUT/$SET"
index=0
for scenario in "${SCENARIOS[@]}"; do
  IFS='|' read -r name primary other motion away others_path <<< "$scenario"
  file=$OUT/$SET/$name.mcap
  extra=()
  [[ -n $away ]] && extra+=(--away "1:$away")
  if [[ -n $others_path ]]; then
    read -r others_motion others_offset <<< "$others_path"
    extra+=(--others-motion "$others_motion" "--others-offset=$others_offset")
  fi
  if [[ ! -f $file ]]; then
    $SIM record --out "$file" --families "$primary" --others "$other" --motion "$motion" \
      "${extra[@]}" --duration $DURATION --decimation 2 --seed $((BASE + index)) >&2
  fi
  index=$((index + 1))
done
cargo run --release --quiet --example detection -- "$OUT/$SET"/*.mcap
echo "command: ./target/release/gdvae-node evaluate $OUT/$SET/*.mcap --config config/objects.toml"
./target/release/gdvae-node evaluate "$OUT/$SET"/*.mcap --config config/objects.toml
