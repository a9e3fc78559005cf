# `make test` is what CI runs (.ci/run): formatting, lints, every test.
CARGO ?= cargo

.PHONY: test lint-docker fmt-check clippy unit build release bench figures peers clean

test: lint-docker fmt-check clippy unit

# hadolint on the Dockerfile (installs a pinned hadolint into .venv-tools/).
lint-docker:
	bash tools/hadolint.sh

fmt-check:
	$(CARGO) fmt --all -- --check

clippy:
	$(CARGO) clippy --all-targets --locked -- -D warnings

unit:
	$(CARGO) test --all-targets --locked

release:
	$(CARGO) build --release --locked

# Criterion benches of the core tick.
bench:
	$(CARGO) bench --bench tick

# The numpy peer of the tick benchmark (creates its own venv).
peers:
	bash benches/peers/run.sh

# Regenerate the committed figures, summaries and result tables of the README.
figures: release
	mkdir -p docs/figures
	./target/release/mcapi experiment hallway --trials 20 --steps 5000 --seed 1 --out out/hallway --no-csv \
	  | tee docs/figures/hallway_results.md
	./target/release/mcapi experiment three-room --trials 20 --steps 10000 --seed 1 --out out/three-room --no-csv \
	  | tee docs/figures/three_room_results.md
	cp out/hallway/fig2* out/three-room/fig3* docs/figures/
	cp out/hallway/summary.json docs/figures/hallway_summary.json
	cp out/three-room/summary.json docs/figures/three_room_summary.json

clean:
	$(CARGO) clean
