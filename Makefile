# `make test` is what CI runs (.ci/run): formatting, lints, every test.
# `make check` is the fast loop while you work; `make help` lists the targets.
CARGO ?= cargo

.DEFAULT_GOAL := test

.PHONY: help check generate test lint-docker check-links fmt-check clippy unit build release bench bench-server bench-vector bench-exactly-once figures peers clean \
	python-venv python-lint python-test e2e contract fuzz checks container-base container-test container-bench \
	k8s-validate k8s-configmap readme-test

CHECKS := lint-docker k8s-validate check-links fmt-check clippy unit contract python-lint python-test e2e readme-test

help: ## lists the targets
	@grep -E '^[a-z0-9-]+:.*## ' $(MAKEFILE_LIST) | sed -E 's/^([a-z0-9-]+):.*## (.*)/  \1|\2/' \
	  | awk -F'|' '{ printf "%-18s %s\n", $$1, $$2 }'

# The contributor's fast loop: formatting, lints and every crate's unit and
# property tests (no integration test, fuzzer, container, browser or Python),
# which also check that the files generated from the parameter tables are up
# to date. A few minutes on a warm tree.
check: fmt-check clippy ## the fast loop: fmt, clippy, unit tests and the generated files (a few minutes warm)
	$(CARGO) test --workspace --lib --bins --locked
	$(CARGO) test --locked -p mcapi-core --tests

# Rewrites the files generated from the parameter tables (docs/sessions.md's
# tables, clients/python/mcapi_client/_params.py); the unit tests fail while
# they differ from the tables.
generate: ## rewrites the files generated from the parameter tables (docs/sessions.md, the Python options)
	MCAPI_BLESS=1 $(CARGO) test --locked -p mcapi-server --lib generated

# The checks run one after the other, as listed; the container's base images
# (network and disk bound, 2-3 minutes from scratch) are made meanwhile, in
# a second job, and the container test runs last. (The sub-make of the
# checks gets MAKEFLAGS without -j, so they stay sequential; variables given
# on the command line still reach them.)
test: ## everything CI runs: lints, every test, contract, Python, browser, container (about 30 min cold)
	@$(MAKE) --no-print-directory -j2 container-base checks
	@$(MAKE) --no-print-directory container-test

checks:
	@MAKEFLAGS='$(filter-out -j% --jobserver-auth=% --jobserver-fds=%,$(MAKEFLAGS))' \
	  $(MAKE) --no-print-directory $(CHECKS)

# The Kubernetes manifests (deploy/k8s/) against the schemas of a named
# Kubernetes version, offline and strictly (unknown fields fail):
# kubernetes-validate, pinned, installed into .venv-tools/ on first use.
# K8S_VERSION=1.33.0 for another version.
k8s-validate: ## the Kubernetes manifests against their schemas, offline
	bash tools/k8s-validate.sh

# Rewrites deploy/k8s/10-mcapi-cluster.yaml (shard map and HAProxy
# configuration) with the debug binary; tests/integration/cluster/kubernetes.rs fails while the
# committed file differs from what this writes.
k8s-configmap: build ## rewrites deploy/k8s/10-mcapi-cluster.yaml with the debug binary
	bash tools/k8s-configmap.sh

# Every relative link in the repository's Markdown resolves (no link out of it).
check-links: ## every relative link in the Markdown resolves
	bash tools/check_links.sh

# hadolint on the Dockerfile (installs a pinned hadolint into .venv-tools/).
lint-docker: ## hadolint on the Dockerfile
	bash tools/hadolint.sh

fmt-check: ## cargo fmt --check
	$(CARGO) fmt --all -- --check

clippy: ## clippy on every crate and target, warnings denied
	$(CARGO) clippy --workspace --all-targets --locked -- -D warnings

unit: ## every Rust test (unit, integration, fuzzer)
	$(CARGO) test --workspace --all-targets --locked

release: ## the release binary (target/release/mcapi)
	$(CARGO) build --release --locked

# The debug binary with the features `unit` builds it with (dev-dependencies
# unify features, so a plain `cargo build` would rebuild much of the tree):
# after `unit` this is a no-op.
build: ## the debug binaries the tests use
	$(CARGO) test --workspace --all-targets --locked --no-run

# The Python client (clients/python) against the debug binary (the one `unit`
# already built, so `make test` compiles no release build): a venv in
# clients/python/.venv, the package installed (not editable) with both
# transports (the rest and grpc extras), its test extras and the extras the
# examples use (gymnasium, plot, mo: MO-Gymnasium with scipy and pygame, about
# 10 s more from the network) at the pinned versions of constraints.txt,
# then pytest.
# `MCAPI_BIN=target/release/mcapi` runs it against the release binary.
PYTHON ?= python3
PY_CLIENT := clients/python
MCAPI_BIN ?= $(CURDIR)/target/debug/mcapi
python-venv: ## the Python client venv (clients/python/.venv) with every extra
	test -x $(PY_CLIENT)/.venv/bin/python || $(PYTHON) -m venv $(PY_CLIENT)/.venv
	rm -rf $(PY_CLIENT)/build  # setuptools would pack stale files left there
	$(PY_CLIENT)/.venv/bin/python -m pip install --quiet --disable-pip-version-check \
	  -c $(PY_CLIENT)/constraints.txt './$(PY_CLIENT)[rest,grpc,test,lint,gymnasium,plot,mo,vector]'

# The client's lints, as clippy is the server's: ruff's rules and mypy
# --strict on the package, its examples and tools (pyproject.toml). The
# tests are not type-checked; `ruff format` is not enforced.
python-lint: python-venv ## ruff and mypy --strict on the Python client
	cd $(PY_CLIENT) && .venv/bin/ruff check . && .venv/bin/mypy

python-test: build python-venv ## the Python client tests against the debug binary
	cd $(PY_CLIENT) && MCAPI_BIN=$(MCAPI_BIN) .venv/bin/pytest

# The REST contract (README, "The contract"): schemathesis (pinned, installed into
# .venv-tools/) against the debug binary with an in-memory store and an API
# key on free ports, every phase (examples, coverage, fuzzing, stateful)
# and every check, 0 failures; then the server must still be up and quick.
# About 2-3 minutes; CONTRACT_MAX_EXAMPLES=200 for a longer run. Reports in
# target/contract/.
contract: build ## schemathesis against a live debug server (the REST contract)
	bash tools/contract.sh

# The generative fuzzer (crates/mcapi-server/tests/fuzz/) for longer than
# `unit` runs it: FUZZ_CASES cases per test (unit: 5000). A failure prints
# its FUZZ_SEED.
FUZZ_CASES ?= 20000
fuzz: ## the generative fuzzer for longer (FUZZ_CASES, default 20000)
	PROPTEST_CASES=$(FUZZ_CASES) $(CARGO) test --locked -p mcapi-server --test fuzz -- --nocapture

# The README's commands as pasted, in order, in one fresh shell against the
# debug binary (tools/readme_test.py): a failing command or an output other
# than the one the README shows fails it. Ports 8080 and 50051 must be free;
# the Python quickstart creates .venv/ (git-ignored) from the network.
readme-test: build ## every command of the README, as pasted
	MCAPI_BIN=$(MCAPI_BIN) python3 tools/readme_test.py

# The dashboard in headless Chromium (tests/e2e): drives a session against
# the debug binary, checks that the charts and the heatmap render and
# update, and writes docs/dashboard.png. Needs Debian's `chromium` (.ci/run
# installs it); skipped with a message when it is missing. `npm ci` installs
# the pinned playwright-core (no browser download).
CHROMIUM ?= $(shell command -v chromium 2>/dev/null || command -v chromium-browser 2>/dev/null)
E2E := tests/e2e
e2e: build ## the dashboard in headless Chromium
	@if [ -z "$(CHROMIUM)" ] || [ ! -x "$(CHROMIUM)" ]; then \
	  echo "e2e skipped: chromium not installed (apt-get install chromium)"; \
	else \
	  cd $(E2E) && npm ci --no-audit --no-fund --loglevel=error && \
	  CHROMIUM="$(CHROMIUM)" MCAPI_BIN="$(MCAPI_BIN)" node dashboard.mjs; \
	fi

# The container image (tools/container-test.sh): built with podman
# from the Dockerfile on locally made base images, then run with a read-only
# root filesystem and a volume, driven over REST and gRPC, stopped with
# SIGTERM and killed with SIGKILL; every acknowledged observation must
# survive. About 10 minutes from scratch (the image's release build). Runs
# wherever podman is installed (.ci/run installs podman, runc and
# debootstrap) and needs root; skipped with a message otherwise.
CONTAINER_OK = command -v podman >/dev/null 2>&1 && { [ "$$(id -u)" -eq 0 ] || sudo -n true 2>/dev/null; }
SUDO_IF_USER = $$([ "$$(id -u)" -eq 0 ] || echo sudo -n env "PATH=$$PATH")
container-base: ## the container base images (rootful podman)
	@if $(CONTAINER_OK); then \
	  mkdir -p target/container; \
	  echo "container-base: making the base images if missing (log: target/container/base.log)"; \
	  $(SUDO_IF_USER) bash tools/container-base.sh >target/container/base.log 2>&1 \
	    || { tail -30 target/container/base.log; exit 1; }; \
	fi

container-test: python-venv container-base ## builds and drives the container image (rootful podman)
	@if ! command -v podman >/dev/null 2>&1; then \
	  echo "container-test skipped: podman not installed (apt-get install podman runc debootstrap)"; \
	elif ! $(CONTAINER_OK); then \
	  echo "container-test skipped: rootful podman needs root or passwordless sudo"; \
	else \
	  $(SUDO_IF_USER) bash tools/container-test.sh; \
	fi

# Start-to-ready time of the container with 10,000 stored sessions, and the
# image size (BENCHMARKS.md); after container-test built the image.
container-bench: python-venv ## start-to-ready time and size of the container image
	bash tools/container-bench.sh

# Criterion benches of the core tick (crates/mcapi-experiments/benches/tick.rs:
# the core stepped by the experiments' simulated world).
bench: ## criterion benches of the core tick
	$(CARGO) bench --bench tick

# Every row of BENCHMARKS.md §8's targets table in one run (benches/server.sh): the server
# pinned to core 0, the load generator to core 1, each target with its
# measurement and ratio (BENCHMARKS.md §8). About 12 minutes; QUICK=1 for a
# short run, MEMORY_SESSIONS=1000000 for the memory row at full size. Not
# part of `make test`.
bench-server: release ## every row of BENCHMARKS.md §8 (about 12 min)
	bash benches/server.sh

# Vectorised stepping (benches/vector.sh, BENCHMARKS.md §13): one Python
# process drives 10,000 hallway agents by StepGroup, InteractBatch and REST,
# server on core 0, client on core 1. About 4 minutes; QUICK=1 for short
# windows. Not part of `make test`.
bench-vector: release python-venv ## vectorised stepping, every path (about 4 min)
	bash benches/vector.sh

# Applied exactly once under a live rebalance and a SIGKILL
# (benches/exactly_once.py, BENCHMARKS.md §13): each run starts `mcapi
# cluster local --replicas 3` on a fresh directory, drives 150 hallway
# sessions through the router with the Python client at its default
# settings, runs `mcapi cluster rebalance --replicas 4` under that load,
# then SIGKILLs one replica, and checks that every session's next_seq is
# the number of observations acknowledged to it. RUNS runs (default 20,
# about 7 minutes on a busy 2-core machine); KILL_DURING=1 kills the replica
# while shards move instead. Exits 1 on a mismatch. Needs haproxy. Not part
# of `make test`.
RUNS ?= 20
bench-exactly-once: python-venv ## exactly once under a rebalance and a SIGKILL, RUNS runs (about 7 min)
	$(CARGO) build --locked --bin mcapi
	$(PY_CLIENT)/.venv/bin/python benches/exactly_once.py --mcapi $(MCAPI_BIN) --runs $(RUNS) \
	  $(if $(filter 1,$(KILL_DURING)),--kill-during)

# The numpy peer of the tick benchmark (creates its own venv).
peers: ## the numpy peer of the tick benchmark
	bash benches/peers/run.sh

# Regenerate the committed figures, summaries and result tables of the README.
figures: release ## regenerates the README's figures and result tables
	mkdir -p docs/figures
	./target/release/mcapi experiment hallway --trials 20 --steps 5000 --seed 1 --out out/hallway --no-csv \
	  | tee docs/figures/hallway_results.md
	./target/release/mcapi experiment three-room --trials 20 --steps 10000 --seed 1 --out out/three-room --no-csv \
	  | tee docs/figures/three_room_results.md
	./target/release/mcapi experiment curiosity --trials 20 --steps 10000 --seed 1 --out out/curiosity --no-csv \
	  | tee docs/figures/curiosity_results.md
	./target/release/mcapi experiment three-room --model learned --trials 20 --steps 10000 --seed 1 --out out/three-room-learned --no-csv \
	  | tee docs/figures/three_room_learned_results.md
	./target/release/mcapi experiment three-room --model learned --slip 0.2 --trials 20 --steps 10000 --seed 1 --out out/three-room-slip --no-csv \
	  | tee docs/figures/three_room_slip_results.md
	cp out/hallway/fig2* out/three-room/fig3* out/curiosity/fig4* docs/figures/
	cp out/three-room-learned/fig3h* out/three-room-learned/fig3i* docs/figures/
	for f in out/three-room-slip/fig3h* out/three-room-slip/fig3i*; do \
	  b=$$(basename $$f); cp $$f docs/figures/$${b%.*}_slip.$${b##*.}; done
	cp out/hallway/summary.json docs/figures/hallway_summary.json
	cp out/three-room/summary.json docs/figures/three_room_summary.json
	cp out/curiosity/summary.json docs/figures/curiosity_summary.json
	cp out/three-room-learned/summary.json docs/figures/three_room_learned_summary.json
	cp out/three-room-slip/summary.json docs/figures/three_room_slip_summary.json

clean: ## cargo clean
	$(CARGO) clean
