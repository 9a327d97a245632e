# The project's entry points. `make test` is what CI runs (.ci/run).
.PHONY: test sim

# Build everything and run every test.
test:
	cargo test --workspace --release

# Build the simulator CLI (target/release/sim).
sim:
	cargo build --release -p gdvae-sim
