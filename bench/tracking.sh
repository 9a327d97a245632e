#!/usr/bin/env bash
# The tracking benchmark: sim recordings with ground truth, generated from fixed seeds, replayed
# through the node by `gdvae-node evaluate`. Three sets of the same 12 scenarios with different
# seeds: `tune` (settings are chosen on it), `holdout` (checked after tuning; one of its plots
# prompted a design change, README says which) and `final` (measured once, nothing chosen on it).
# `extra-N` (N = 1, 2, ...) are more held-apart seeds, for a choice between candidates whose
# difference on `tune` is within what one set of 12 recordings can tell apart.
#
# `dense-tune`, `dense-holdout` and `dense-final` are the same scenarios at the sim's own defaults
# for the camera (every depth pixel, a 4 m ground patch: about 120,000 points a frame, four times
# the others'), from seeds of their own: what a dense sensor gives, floor noise included.
#
# `idle-tune` and `idle-holdout` are a stress set of idle bipeds at the sim's own camera defaults
# and beyond: three seeds each with the default camera, one 2.2 m up, one 4.5 m away, one 2.2 m
# away, and six clutter objects (seeds 5001-5043 and 5501-5543; docs/tracking.md "A body in
# pieces"). No subject changes: every change reported is a false one.
#
# `still-tune` and `still-holdout` are idle bipeds at the sim's camera defaults for longer and at
# lower frame rates: three seeds each of 30 s at 30 Hz, 16 s at 15 Hz and 20 s at 10 Hz (seeds
# 7001-7023 and 7101-7123; docs/tracking.md "Standing subjects").
#
# `idle-extra-N` and `still-extra-N` are more held-apart seeds of those two kinds (N = 1: seeds
# 20101-20143 and 30101-30123; each N after, 100 more): an idle set holds few recordings, and one
# recording whose track goes astray moves its p90 by many degrees.
#
# `fit-N` (N = 1, 2, ...; seeds 60000 + 100 N onwards) are the 12 scenarios again, for what is
# fitted on the node's own clouds (bench/change_detector.py's discriminant; docs/tracking.md "The
# change detector replayed"); never reported as benchmark figures.
#
# `stand-tune`, `stand-holdout` and `stand-final` are the 12 scenarios with every idle subject
# standing instead (`sim record --motion stand`: idle's place and turn, a walking subject's small
# pose drift; seeds 40000-40011, 40100-40111, 40200-40211): beside the walks, what the pose code
# does while the pose holds still (`evaluate`'s "pose code z_E" line; issue 32's walking / standing
# spread).
#
#   bench/tracking.sh SET [OUT_DIR] [-- evaluate options...]
#
# SET is tune, holdout or final. Recordings go to OUT_DIR/SET/ (default /work/data/bench-tracking, or
# $BENCH_DIR) and are made once (the sim is deterministic per seed); the report goes to
# OUT_DIR/SET.json and the plots to OUT_DIR/SET-plots/.
set -euo pipefail
cd "$(dirname "$0")/.."

SET=${1:?usage: bench/tracking.sh [dense-]tune|holdout|final|extra-N|idle-tune|idle-holdout|idle-extra-N|still-tune|still-holdout|still-extra-N|stand-tune|stand-holdout|stand-final|fit-N [OUT_DIR] [-- evaluate options]}
shift
OUT=${BENCH_DIR:-/work/data/bench-tracking}
if [[ $# -gt 0 && $1 != "--" ]]; then OUT=$1; shift; fi
[[ ${1:-} == "--" ]] && shift
CAMERA=(--decimation 2 --ground-extent 1.5)
case $SET in
  dense-idle-*|dense-still-*) echo "bench/tracking.sh: the idle sets are at the sim's camera defaults already: use ${SET#dense-}" >&2; exit 2 ;;
  dense-stand-*) echo "bench/tracking.sh: no dense stand sets: use ${SET#dense-}" >&2; exit 2 ;;
  dense-*) CAMERA=(--decimation 1 --ground-extent 4); KIND=${SET#dense-}; OFFSET=5000 ;;
  idle-*|still-*) KIND=$SET; OFFSET=0 ;;
  *) KIND=$SET; OFFSET=0 ;;
esac
case $KIND in
  idle-tune) BASE=5000 ;;
  idle-holdout) BASE=5500 ;;
  still-tune) BASE=7000 ;;
  still-holdout) BASE=7100 ;;
  idle-extra-[1-9]|idle-extra-[1-9][0-9]) BASE=$((20000 + 100 * ${KIND#idle-extra-})) ;;
  still-extra-[1-9]|still-extra-[1-9][0-9]) BASE=$((30000 + 100 * ${KIND#still-extra-})) ;;
  stand-tune) BASE=40000 ;;
  stand-holdout) BASE=40100 ;;
  stand-final) BASE=40200 ;;
  tune) BASE=100 ;;
  holdout) BASE=200 ;;
  final) BASE=300 ;;
  extra-[1-9]|extra-[1-9][0-9]) BASE=$((1000 + 100 * ${KIND#extra-})) ;;
  fit-[1-9]|fit-[1-9][0-9]) BASE=$((60000 + 100 * ${KIND#fit-})) ;;
  *) echo "bench/tracking.sh: unknown set '$SET' (tune, holdout, final or extra-N, each also as dense-...; idle-tune, idle-holdout, idle-extra-N, still-tune, still-holdout, still-extra-N, stand-tune, stand-holdout, stand-final, fit-N)" >&2; exit 2 ;;
esac
BASE=$((BASE + OFFSET))

SIM=./target/release/sim
NODE=./target/release/gdvae-node
for binary in $SIM $NODE; do
  [[ -x $binary ]] || { echo "bench/tracking.sh: $binary missing: run 'make node sim' first" >&2; exit 2; }
done

# name | motion | families (cycled at each switch) | duration s | switch times s | camera distance m
SCENARIOS=(
  "walk-qq|walk|quadruped|8|4|2.6"
  "walk-bb|walk|biped|8|4|3.2"
  "walk-qqq|walk|quadruped|9|3,6|3.6"
  "walk-bbb|walk|biped|9|3,6|2.8"
  "idle-qq|idle|quadruped|8|4|2.6"
  "idle-bb|idle|biped|8|4|3.2"
  "walk-qb|walk|quadruped,biped|8|4|3.0"
  "walk-bq|walk|biped,quadruped|8|4|3.4"
  "idle-q|idle|quadruped|8||3.0"
  "idle-b|idle|biped|8||2.6"
  "walk-q|walk|quadruped|8||3.5"
  "walk-b|walk|biped|8||2.4"
)

# The idle sets: name | seed offset | camera options (the sim's defaults otherwise).
IDLE_GROUPS=(
  "default|0|"
  "high|10|--camera-height 2.2"
  "far|20|--camera-distance 4.5"
  "near|30|--camera-distance 2.2"
  "clutter|40|--clutter 6"
)

mkdir -p "$OUT/$SET"
RECORDINGS=()
# record NAME SEED SIM-OPTIONS...: OUT/SET/NAME-sSEED.mcap joins the set, made once (the sim is
# deterministic per seed; a half-written file never passes for a recording).
record() {
  local file="$OUT/$SET/$1-s$2.mcap" seed=$2
  shift 2
  RECORDINGS+=("$file")
  [[ -s $file ]] && return
  local args=(record --out "$file.partial" "$@" --seed "$seed")
  echo "bench/tracking.sh: $SIM ${args[*]}" >&2
  $SIM "${args[@]}" >&2
  mv "$file.partial" "$file"
}
if [[ $KIND == idle-* ]]; then
  for group in "${IDLE_GROUPS[@]}"; do
    IFS='|' read -r name offset options <<<"$group"
    for n in 1 2 3; do
      # shellcheck disable=SC2086 # the options are words
      record "$name" $((BASE + offset + n)) --motion idle --families biped --duration 8 $options
    done
  done
  SCENARIOS=()
fi
# The still sets: name | seed offset | frame rate | duration s.
STILL_GROUPS=(
  "long|0|30|30"
  "fps15|10|15|16"
  "fps10|20|10|20"
)
if [[ $KIND == still-* ]]; then
  for group in "${STILL_GROUPS[@]}"; do
    IFS='|' read -r name offset fps duration <<<"$group"
    for n in 1 2 3; do
      record "$name" $((BASE + offset + n)) --motion idle --families biped --duration "$duration" --fps "$fps"
    done
  done
  SCENARIOS=()
fi
index=0
for scenario in "${SCENARIOS[@]}"; do
  IFS='|' read -r name motion families duration switches distance <<<"$scenario"
  if [[ $KIND == stand-* && $motion == idle ]]; then
    name=stand${name#idle}
    motion=stand
  fi
  seed=$((BASE + index))
  index=$((index + 1))
  switch_at=()
  [[ -n $switches ]] && switch_at=(--switch-at "$switches")
  record "$name" "$seed" --motion "$motion" --families "$families" --duration "$duration" \
    --camera-distance "$distance" "${CAMERA[@]}" "${switch_at[@]}"
done

$NODE evaluate "${RECORDINGS[@]}" --config config/replay.toml \
  --out "$OUT/$SET.json" --plots "$OUT/$SET-plots" "$@"
