# The project's entry points. `make test` is what CI runs (.ci/run).
.PHONY: test test-rust test-python sim venv samples

VENV := .venv
PYTHON := $(VENV)/bin/python
REQUIREMENTS := sim/requirements.txt models/pyproject.toml

# Build everything and run every test: Rust, then the Python checks against the built binaries.
# The venv comes first: the node's tests load ONNX Runtime from its onnxruntime wheel.
test: test-rust test-python

test-rust: venv
	cargo test --workspace --release

test-python: venv sim
	$(PYTHON) -m pytest -q sim/tests/python
	cd models && ../$(PYTHON) -m pytest -q tests

# Build the simulator CLI (target/release/sim).
sim:
	cargo build --release -p gdvae-sim

# The project's Python environment, rebuilt when a requirements file changes.
venv: $(VENV)/.installed
$(VENV)/.installed: $(REQUIREMENTS)
	python3 -m venv $(VENV)
	$(PYTHON) -m pip install --quiet --upgrade pip
	$(PYTHON) -m pip install --quiet -r sim/requirements.txt
	$(PYTHON) -m pip install --quiet -e 'models[test]'
	touch $@

# The committed samples (sim/samples/): regenerate them with exactly these commands.
samples: sim
	./target/release/sim record --out sim/samples/walk_switch.mcap --families quadruped,biped \
		--duration 5 --switch-at 2.5 --decimation 2 --ground-extent 1.2 --camera-distance 2.6 --seed 0
	for family in quadruped biped; do \
		for pose in rest gaussian bent; do \
			./target/release/sim mesh --family $$family --pose $$pose --subject-seed 1 --pose-seed 1 \
				--out sim/samples/meshes/$${family}_$${pose}.ply; \
		done; \
	done
