# The project's entry points. `make test` is what CI runs (.ci/run).
.PHONY: demo test test-rust test-python binaries sim node venv onnxruntime samples bench-tracking bench-tracking-dense bench-tracking-idle bench-tracking-stand fit-identity bench-multi fuzz soak eval-split device-job

VENV := .venv
PYTHON := $(VENV)/bin/python
REQUIREMENTS := sim/requirements.txt models/pyproject.toml
# pip keeps no second copy of the wheels it downloads (PyPI's torch brings ~4 GB of CUDA libraries
# on Linux): a clone after `make test` holds 9.6 GiB, most of it the venv and target/.
PIP := $(PYTHON) -m pip install --quiet --no-cache-dir

# The node's demo: the shipped bundle on the shipped sample recording (30 Hz, original timing),
# publishing on an embedded zenoh peer, with a line per state on stdout. Needs only ONNX Runtime.
demo: onnxruntime node
	./target/release/gdvae-node run --config config/default.toml --live-summary

# The node's binary, built exactly as the tests build it (same features, same profile), so that
# `make demo` after `make test`, or the other way round, compiles nothing again.
node: binaries

# Build everything and run every test: Rust, then the Python checks against the built binaries.
# The venv comes first: the node's tests load ONNX Runtime from its onnxruntime wheel.
test: test-rust test-python

test-rust: venv
	cargo test --workspace --release

test-python: venv binaries
	$(PYTHON) -m pytest -q sim/tests/python tests/python
	cd models && ../$(PYTHON) -m pytest -q tests

# The binaries the Python checks run (target/release/sim, gdvae-node), built exactly as the Rust
# tests build them, so that after `test-rust` nothing is compiled a second time.
binaries:
	cargo test --workspace --release --no-run

# The tracking benchmark (docs/tracking.md "Tracking benchmark"): settings are chosen on `tune`, checked on
# `holdout` and `final`. Recordings are made once into $(BENCH_DIR) (default /work/data/bench-tracking).
bench-tracking: onnxruntime node sim
	bench/tracking.sh tune
	bench/tracking.sh holdout
	bench/tracking.sh final

# The same scenarios at the sim's own camera defaults (every depth pixel; 1.4 GB of recordings a set).
bench-tracking-dense: onnxruntime node sim
	bench/tracking.sh dense-tune
	bench/tracking.sh dense-holdout
	bench/tracking.sh dense-final

# Idle bipeds at the sim's camera defaults and beyond (near, high, far, clutter): false changes and heading;
# and standing for 30 s, or at 15 and 10 Hz (docs/tracking.md "Standing subjects").
bench-tracking-idle: onnxruntime node sim
	bench/tracking.sh idle-tune
	bench/tracking.sh idle-holdout
	bench/tracking.sh still-tune
	bench/tracking.sh still-holdout
	bench/tracking.sh idle-extra-1
	bench/tracking.sh idle-extra-2
	bench/tracking.sh still-extra-1

# The 12 scenarios with standing subjects instead of idle ones (a walker's small pose drift): what the
# pose code z_E does during a walk against while the pose holds still (docs/tracking.md "A pose that holds still").
bench-tracking-stand: onnxruntime node sim
	bench/tracking.sh stand-tune
	bench/tracking.sh stand-holdout
	bench/tracking.sh stand-final

# The default bundle's identity projection fitted again on the node's own clouds of the fit sets
# (bench/tracking.sh fit-1..16; models/README "Identity projection"): after its encoder changes,
# since the node drops a projection fitted on another encoder (and finds changes on z_I). States in
# /work/data/bench-tracking, or $BENCH_DIR.
FIT_STATES := $(or $(BENCH_DIR),/work/data/bench-tracking)
fit-identity: onnxruntime node sim venv
	for n in $$(seq 1 16); do bench/tracking.sh fit-$$n -- --states $(FIT_STATES)/fit-$$n-states.jsonl; done
	cd models && ../$(PYTHON) -m gdvae fit-identity bundles/h200-fo-nodeid $(FIT_STATES)/fit-*-states.jsonl

# The multi-object benchmark (docs/tracking.md "Several objects"): its recordings, the candidate
# detection and the tracking (evaluate with config/objects.toml) on `tune`, `holdout`, `final`, the
# re-identification set `returns`, the crossing-paths set `cross` and `three` (three subjects). Recordings in
# /work/data/bench-multi, or $BENCH_DIR.
bench-multi: sim
	bench/multi_object.sh tune
	bench/multi_object.sh holdout
	bench/multi_object.sh final
	bench/multi_object.sh returns
	bench/multi_object.sh cross
	bench/multi_object.sh three

# The paper-structured evaluation set (models/README.md "Evaluation split"): 300 subjects per
# family, one pose each, all in the test split, from a seed no training set uses.
EVAL_DIR ?= /work/data/sim-eval
eval-split: sim
	./target/release/sim dataset --out $(EVAL_DIR) --subjects 300 --poses 1 --split 0,0,1 --seed 9000

# What the GPU recipe's device job (models/device/run.sh) carries: .device/wheels (what the device's
# Python lacks), .device/spectra (the spectra of DEVICE_DATA, the dataset the job regenerates
# there from the same seed) and .device/init (DEVICE_INIT, the bundle whose autoencoder it
# continues: the best so far, the H200's, when ../shared has it). Then: run with carry
# [".device", "target/release/sim"] and the command `bash models/device/run.sh`
# (models/README.md, "Training on a lent GPU").
DEVICE_DATA ?= /work/data/sim-device
DEVICE_INIT ?= ../shared/bundles/h200-ae46k-fo
device-job: venv sim
	test -d $(DEVICE_DATA) || ./target/release/sim dataset --out $(DEVICE_DATA) --subjects 480 --poses 5 --seed 1
	$(PYTHON) -m gdvae spectra $(DEVICE_DATA) --count 22 >/dev/null
	rm -rf .device/spectra && mkdir -p .device/wheels .device/spectra
	cp $(DEVICE_DATA)/.spectra/*.npy .device/spectra/
	$(PYTHON) -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.12 \
		--implementation cp --platform manylinux2014_x86_64 -d .device/wheels trimesh==5.2.0
	rm -rf .device/init
	if test -f $(DEVICE_INIT)/manifest.json; then mkdir -p .device/init && \
		cp $(DEVICE_INIT)/manifest.json $(DEVICE_INIT)/*.onnx .device/init/; fi
	du -sh .device

# Overload soak (docs/faults.md): a live feed at SOAK_FACTOR times the node's
# capacity for SOAK_SECONDS against the real binary; prints the RSS series, drops and latency.
SOAK_FACTOR ?= 10
SOAK_SECONDS ?= 60
soak: venv onnxruntime node
	$(PYTHON) bench/soak.py --factor $(SOAK_FACTOR) --seconds $(SOAK_SECONDS)

# Fuzz every decoder that takes outside bytes for FUZZ_SECONDS each (cargo-fuzz on the nightly
# toolchain; installed here if missing). Not part of `make test`: findings become regression tests.
# Inputs are held to 64 KiB: the uncompressed seed recording (1.5 MB) otherwise sets the limit and
# halves the rate; a recording cut at 64 KiB is itself a useful input.
FUZZ_SECONDS ?= 300
FUZZ_TARGETS ?= mcap cdr files prepare rosbag2
fuzz: venv sim
	cargo +nightly fuzz --version >/dev/null 2>&1 || cargo +nightly install cargo-fuzz --locked
	fuzz/seed.sh
	for target in $(FUZZ_TARGETS); do \
		cargo +nightly fuzz run $$target -- -max_total_time=$(FUZZ_SECONDS) -rss_limit_mb=2048 \
			-max_len=65536 -timeout=10 -print_final_stats=1 || exit 1; \
	done

# The simulator CLI (target/release/sim), built as the tests build it.
sim: binaries

# ONNX Runtime for the node: the onnxruntime wheel's libonnxruntime.so, in .venv (never downloaded
# at build or run time; the node finds it there, or at ORT_DYLIB_PATH).
onnxruntime: $(VENV)/.onnxruntime
$(VENV)/.onnxruntime:
	test -x $(PYTHON) || python3 -m venv $(VENV)
	$(PIP) onnxruntime==1.31.1
	touch $@

# The project's Python environment, rebuilt when a requirements file changes.
venv: $(VENV)/.installed
$(VENV)/.installed: $(REQUIREMENTS)
	@free=$$(df -Pk . | awk 'NR==2 {print int($$4 / 1048576)}'); \
		if [ "$$free" -lt 12 ]; then echo "warning: $$free GiB free here; a fresh venv and build take about 10 GiB" >&2; fi
	python3 -m venv $(VENV)
	$(PIP) --upgrade pip
	$(PIP) -r sim/requirements.txt
	$(PIP) -e 'models[test]'
	touch $@

# The committed samples (sim/samples/): regenerate them with exactly these commands.
samples: sim
	./target/release/sim record --out sim/samples/walk_switch.mcap --families quadruped,biped \
		--duration 5 --switch-at 2.5 --decimation 2 --ground-extent 1.2 --camera-distance 2.6 --seed 0
	./target/release/sim record --out sim/samples/two_subjects.mcap --families quadruped --others biped \
		--motion walk --away 1:2-3.5 --duration 6 --decimation 2 --fps 10 --seed 11
	for family in quadruped biped; do \
		for pose in rest gaussian bent; do \
			./target/release/sim mesh --family $$family --pose $$pose --subject-seed 1 --pose-seed 1 \
				--out sim/samples/meshes/$${family}_$${pose}.ply; \
		done; \
	done
