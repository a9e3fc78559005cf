# `make test` is what CI runs (.ci/run): formatting, lints, every test.
CARGO ?= cargo

.PHONY: test lint-docker fmt-check clippy unit build release bench figures peers clean python-test e2e contract fuzz

test: lint-docker fmt-check clippy unit contract python-test e2e

# hadolint on the Dockerfile (installs a pinned hadolint into .venv-tools/).
lint-docker:
	bash tools/hadolint.sh

fmt-check:
	$(CARGO) fmt --all -- --check

clippy:
	$(CARGO) clippy --workspace --all-targets --locked -- -D warnings

unit:
	$(CARGO) test --workspace --all-targets --locked

release:
	$(CARGO) build --release --locked

# The debug binary with the features `unit` builds it with (dev-dependencies
# unify features, so a plain `cargo build` would rebuild much of the tree):
# after `unit` this is a no-op.
build:
	$(CARGO) test --workspace --all-targets --locked --no-run

# The Python client (clients/python) against the debug binary (the one `unit`
# already built, so `make test` compiles no release build): a venv in
# clients/python/.venv, the package installed (not editable) with its test
# extras at the pinned versions of constraints.txt, then pytest.
# `MCAPI_BIN=target/release/mcapi` runs it against the release binary.
PYTHON ?= python3
PY_CLIENT := clients/python
MCAPI_BIN ?= $(CURDIR)/target/debug/mcapi
python-test: build
	test -x $(PY_CLIENT)/.venv/bin/python || $(PYTHON) -m venv $(PY_CLIENT)/.venv
	rm -rf $(PY_CLIENT)/build  # setuptools would pack stale files left there
	$(PY_CLIENT)/.venv/bin/python -m pip install --quiet --disable-pip-version-check \
	  -c $(PY_CLIENT)/constraints.txt './$(PY_CLIENT)[test,gymnasium,plot]'
	cd $(PY_CLIENT) && MCAPI_BIN=$(MCAPI_BIN) .venv/bin/pytest

# The REST contract (issue 12): schemathesis (pinned, installed into
# .venv-tools/) against the debug binary with an in-memory store and an API
# key on free ports, every phase (examples, coverage, fuzzing, stateful)
# and every check, 0 failures; then the server must still be up and quick.
# About 2-3 minutes; CONTRACT_MAX_EXAMPLES=200 for a longer run. Reports in
# target/contract/.
contract: build
	bash tools/contract.sh

# The generative fuzzer (tests/fuzz.rs) for longer than `unit` runs it:
# FUZZ_CASES cases per test (unit: 5000). A failure prints its FUZZ_SEED.
FUZZ_CASES ?= 20000
fuzz:
	PROPTEST_CASES=$(FUZZ_CASES) $(CARGO) test --locked --test fuzz -- --nocapture

# The dashboard in headless Chromium (tests/e2e): drives a session against
# the debug binary, checks that the charts and the heatmap render and
# update, and writes docs/dashboard.png. Needs Debian's `chromium` (.ci/run
# installs it); skipped with a message when it is missing. `npm ci` installs
# the pinned playwright-core (no browser download).
CHROMIUM ?= $(shell command -v chromium 2>/dev/null || command -v chromium-browser 2>/dev/null)
E2E := tests/e2e
e2e: build
	@if [ -z "$(CHROMIUM)" ] || [ ! -x "$(CHROMIUM)" ]; then \
	  echo "e2e skipped: chromium not installed (apt-get install chromium)"; \
	else \
	  cd $(E2E) && npm ci --no-audit --no-fund --loglevel=error && \
	  CHROMIUM="$(CHROMIUM)" MCAPI_BIN="$(MCAPI_BIN)" node dashboard.mjs; \
	fi

# Criterion benches of the core tick (crates/mcapi-experiments/benches/tick.rs:
# the core stepped by the experiments' simulated world).
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
	./target/release/mcapi experiment curiosity --trials 20 --steps 10000 --seed 1 --out out/curiosity --no-csv \
	  | tee docs/figures/curiosity_results.md
	cp out/hallway/fig2* out/three-room/fig3* out/curiosity/fig4* docs/figures/
	cp out/hallway/summary.json docs/figures/hallway_summary.json
	cp out/three-room/summary.json docs/figures/three_room_summary.json
	cp out/curiosity/summary.json docs/figures/curiosity_summary.json

clean:
	$(CARGO) clean
