#!/usr/bin/env bash
# The GPU recipe as one job for a lent device machine (models/README.md, "Training on a lent GPU").
#
# Why a script: a lent accelerator comes for minutes, bare, with no network, so everything the job
# needs travels with it (`make device-job` prepares .device/ here: the wheels its Python lacks and
# the dataset's spectra) and everything it makes comes back through $OUT (at most 8 files of
# 16 MiB): the bundle (5 files), train.log, log.jsonl and run.json (recipe and stages.json).
# Run there from the repository root, carrying `.device` and `target/release/sim`:
#     bash models/device/run.sh
# It first runs itself at smoke size on the same device (a few subjects, seconds per stage), so
# that a bug on the accelerator's path costs a minute of the lease, not all of it. The same script
# runs on a CPU at smoke size (`DEVICE=cpu RECIPE=smoke ...`): that is its test.
set -euo pipefail

OUT=${OUT:?set OUT to the folder whose files come back}
DEVICE=${DEVICE:-cuda}
RECIPE=${RECIPE:-gpu}
AE_MINUTES=${AE_MINUTES:-5.5}      # the stage budgets: 7 minutes of training, and with the smoke
VAE_MINUTES=${VAE_MINUTES:-1.5}    # step, data and export inside one 10-minute command
# The dataset: 480 subjects x 5 poses per family, 384 training subjects each (`make device-job`
# computes its spectra here). The shipped bundles had 60 x 20 (96 training subjects), which the
# H200's autoencoder memorised within 5 minutes (its held-out d_C did not move).
SUBJECTS=${SUBJECTS:-480}
POSES=${POSES:-5}
SEED=${SEED:-1}
# The bundle whose autoencoder is trained on (import-bundle): what `make device-job` put in
# .device/init (the best so far), else the shipped one; empty: a fresh AE.
DEFAULT_INIT=models/bundles/cpu-fo
[ -f .device/init/manifest.json ] && DEFAULT_INIT=.device/init
INIT=${INIT-$DEFAULT_INIT}
REGIME=${REGIME:-fo}
LEARNING_RATE=${LEARNING_RATE:-3e-4}
DEADLINE_S=${DEADLINE_S:-570}      # the whole job, inside the device tool's 600-second command
RESERVE_S=${RESERVE_S:-90}         # the code bank, the export and its calibration, after the VAE
DEPTH_CAMERA=${DEPTH_CAMERA:-1}    # 1: partial views as the depth camera renders them (what the node sees)
WORKERS=${WORKERS:-0}              # loader processes, CPU only: on a GPU the batches are made on it
SMOKE_FIRST=${SMOKE_FIRST:-1}      # 0: skip the smoke step (the smoke step itself runs with 0)
PYTHON=${PYTHON:-python3}
SIM=${SIM:-target/release/sim}
WORK=${WORK:-/tmp/gdvae-device}
started=$(date +%s)
say() { echo "[device job, ${SECONDS}s] $*"; }

rm -rf "$WORK" && mkdir -p "$WORK" "$OUT"
if compgen -G ".device/wheels/*.whl" >/dev/null; then
    "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$WORK/site" .device/wheels/*.whl
    export PYTHONPATH="$WORK/site${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$PWD/models${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
"$PYTHON" -c "import torch, trimesh; print('torch', torch.__version__, 'device', '$DEVICE',
    torch.cuda.get_device_name() if '$DEVICE'.startswith('cuda') else '')"

# The dataset is generated on the CPU cores while the smoke step runs on the device.
say "dataset: $SUBJECTS subjects x $POSES poses per family, seed $SEED"
"$SIM" dataset --out "$WORK/data" --subjects "$SUBJECTS" --poses "$POSES" --seed "$SEED" >"$WORK/dataset.log" 2>&1 &
dataset=$!

if [ "$SMOKE_FIRST" = 1 ]; then
    say "smoke step: this job at smoke size on $DEVICE (log: $WORK/smoke.log)"
    if ! OUT="$WORK/smoke-out" WORK="$WORK/smoke" SMOKE_FIRST=0 SUBJECTS=5 POSES=2 AE_MINUTES=0.05 \
            VAE_MINUTES=0.05 bash "$0" >"$WORK/smoke.log" 2>&1; then
        kill "$dataset" 2>/dev/null || true
        cp "$WORK/smoke.log" "$OUT/smoke.log"
        tail -n 40 "$WORK/smoke.log"
        say "the smoke step failed: nothing trained (its log is in \$OUT/smoke.log)"
        exit 1
    fi
    say "smoke step passed"
fi
if ! wait "$dataset"; then
    cat "$WORK/dataset.log"
    say "the dataset could not be generated"
    exit 1
fi
say "dataset ready"
if compgen -G ".device/spectra/*.npy" >/dev/null; then  # computed here once: the cache is keyed by geometry
    mkdir -p "$WORK/data/.spectra" && cp .device/spectra/*.npy "$WORK/data/.spectra/"
fi

# The AE's budget gives way when the smoke step and the data took longer than planned, so that
# the bank, the VAE and the export still end before DEADLINE_S (the tool kills the command at 600 s
# and a killed job returns no bundle).
elapsed=$(( $(date +%s) - started ))
AE_MINUTES=$("$PYTHON" -c "import sys; planned, left = float(sys.argv[1]), (float(sys.argv[2]) - float(sys.argv[3])
    - 60 * float(sys.argv[4]) - float(sys.argv[5])) / 60; print(round(max(0.05, min(planned, left)), 2))" \
    "$AE_MINUTES" "$DEADLINE_S" "$elapsed" "$VAE_MINUTES" "$RESERVE_S")
say "AE budget: $AE_MINUTES min (${elapsed} s spent; the job ends by ${DEADLINE_S} s)"
args=(--recipe "$RECIPE" --regime "$REGIME" --device "$DEVICE" --ae-minutes "$AE_MINUTES"
      --vae-minutes "$VAE_MINUTES" --loader-workers "$WORKERS" --set vae.omega_jacobian=0
      --set "recipe.ae_learning_rate=$LEARNING_RATE")
if [ "$DEPTH_CAMERA" = 1 ]; then args+=(--set recipe.depth_camera_views=true); fi
if [ -n "$INIT" ]; then
    say "importing $INIT"
    "$PYTHON" -m gdvae import-bundle "$INIT" --out "$WORK/imported"
    args+=(--init-from "$WORK/imported" --continue-ae 10000000)  # the AE budget ends it
else
    args+=(--ae std --partial-views 0.75 --set ae.rotation_head=yaw)
fi
say "training: ${args[*]}"
"$PYTHON" -m gdvae train "$WORK/data" --out "$WORK/run" "${args[@]}" 2>&1 | tee "$OUT/train.log"

say "export (with the z_I variance calibration on the held-out subjects)"
"$PYTHON" -m gdvae export "$WORK/run" --out "$OUT/bundle" --calibrate "$WORK/data" 2>&1 | tee -a "$OUT/train.log"
cp "$WORK/run/log.jsonl" "$OUT/"
"$PYTHON" - "$WORK/run" "$OUT/run.json" <<'PY'
import json, pathlib, sys
run = pathlib.Path(sys.argv[1])
record = {"recipe": json.loads((run / "recipe.json").read_text()), "stages": json.loads((run / "stages.json").read_text())}
pathlib.Path(sys.argv[2]).write_text(json.dumps(record, indent=2))
PY
say "done in $(( $(date +%s) - started )) s: $OUT/bundle"
