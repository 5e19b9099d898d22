# The two commands of the quick start: `make run` and `make test`.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
TYPECHECK := .mypy_cache/tree/ride_machine

.PHONY: run test test-under-load install browser prometheus js schema states hazards lint bench clean

# The locked versions (requirements/dev.txt, hashes checked), then the project itself on top.
$(STAMP): pyproject.toml requirements/dev.txt requirements/neighbours.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet --require-hashes -r requirements/dev.txt
	$(BIN)/python -m pip install --quiet --no-deps --no-build-isolation -e .
	$(BIN)/python -m pip download --quiet --no-deps --require-hashes -r requirements/neighbours.txt \
	  --dest $(VENV)/wheels
	touch $(STAMP)

install: $(STAMP)

## Install, then run the daemon on the simulator with the example config.
run: $(STAMP)
	$(BIN)/machine run --sim --config machine.toml

## Debian's Chromium for the UI's browser tests (installed when root with apt, as on CI;
## elsewhere the browser tests skip and say why).
browser:
	@command -v chromium >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; \
	  else echo "chromium not installed: the browser tests will be skipped"; fi; }

## Debian's Prometheus server and promtool for the gateway's metrics tests (installed when root
## with apt, as on CI; elsewhere those tests skip and say why).
prometheus:
	@command -v promtool >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends prometheus >/dev/null; \
	  else echo "prometheus not installed: the gateway's Prometheus tests will be skipped"; fi; }

## The tests' Node packages, each pinned by its package-lock.json: ajv for the JSON Schema check
## and axe-core for the UI's accessibility check (tests/js), node-opcua's client for the
## gateway's OPC UA check (tests/gateway/js); when node and npm are present; without them those
## tests skip and say why. `npm ci` runs only when package-lock.json is newer than the copy npm
## keeps in node_modules (its hidden lockfile, touched here after each install): offline, an
## installed tree is used as it is (npm ci would delete it and wait on the registry).
JS_STAMPS := tests/js/node_modules/.package-lock.json \
	tests/gateway/js/node_modules/.package-lock.json
js: $(JS_STAMPS)

%/node_modules/.package-lock.json: %/package-lock.json
	@if command -v npm >/dev/null 2>&1; then \
	  npm ci --prefix $* --no-audit --no-fund --silent && touch $@; \
	else echo "npm not installed: the checks of $* will be skipped"; fi

## Regenerate the checked-in JSON Schema (schema/json/) from the models.
schema: $(STAMP)
	$(BIN)/machine schema schema/json

## Regenerate the README's state table and docs/states.md from the transition table
## (service/core/statemachine/table.py TABLE); tests/service/core/statemachine/test_control_doc.py fails while they differ.
states: $(STAMP)
	$(BIN)/python -m ride_machine.service.core.statemachine.control_doc

## Run every test the hazard log names, record the results and rewrite docs/hazards.md from
## docs/hazards.toml (tests/test_hazards.py fails while the page, the table and the suite differ).
hazards: $(STAMP)
	$(BIN)/python -m tests.hazard_log --run

## Install, then lint, type-check and run the whole test suite: two pytest-xdist workers, each
## taking a whole test file at a time (a file's tests share fixtures and daemons).
## PARALLEL= runs it in one process.
PARALLEL ?= -n 2 --dist loadfile
test: $(STAMP) browser prometheus js $(TYPECHECK)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/python -m pytest $(PARALLEL)

## The whole suite beside one CPU-bound process per core, as a busy CI host runs it;
## ORDER=reverse or ORDER=random (random:SEED to repeat one) changes the order of the tests.
ORDER ?= normal
test-under-load: $(STAMP) browser js $(TYPECHECK)
	$(BIN)/python -m tests.under_load $(PARALLEL) --order $(ORDER)

lint: $(STAMP) $(TYPECHECK)
	$(BIN)/ruff check .
	$(BIN)/mypy

## mypy reads the code under the name it is installed as (ride_machine.<folder>, pyproject.toml's
## package-dir): a tree of links to the folders, in mypy's own cache folder.
$(TYPECHECK):
	mkdir -p $@
	for p in schema common hal service sim rider; do ln -sfn ../../../$$p $@/$$p; done

## Run every benchmark and rewrite BENCHMARKS.md.
bench: $(STAMP)
	$(BIN)/python -m bench.all

## Refresh the lock files (requirements/README.md) after a range in pyproject.toml changed;
## `make lock UPGRADE=1` also takes the newest releases within the ranges.
LOCK = $(BIN)/pip-compile --quiet --generate-hashes --allow-unsafe --strip-extras \
	--no-emit-index-url --no-emit-find-links $(if $(UPGRADE),--upgrade)
lock: $(STAMP)
	$(BIN)/python -m pip install --quiet "pip-tools>=7.5,<8"
	$(LOCK) --extra dev --extra revpi --extra ui --extra gateway --all-build-deps \
	  -o requirements/dev.txt pyproject.toml
	$(LOCK) --extra revpi --extra ui --extra gateway -c requirements/dev.txt -o requirements/runtime.txt pyproject.toml
	$(LOCK) --extra revpi --extra ui -c requirements/dev.txt -o requirements/machine.txt pyproject.toml
	$(LOCK) --all-build-deps --only-build-deps -c requirements/dev.txt \
	  -o requirements/build.txt pyproject.toml

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache tests/js/node_modules \
	  tests/gateway/js/node_modules
