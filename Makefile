# twohr: `make demo` runs the main job end to end; `make test` runs the suite (and builds the docs first).
# Both create .venv and install everything on first use.
SHELL := /bin/bash
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml | sha256sum | cut -c1-12)
DEMO_SEQUENCE ?= ../shared/data/rgbd_bonn_crowd_dev
DEMO_OUT ?= runs/demo

.PHONY: demo test compose-test venv models lint clean test-prerequisites docs

venv: $(STAMP)

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; assert sys.version_info[:2] == (3, 11), "twohr needs Python 3.11, found " + sys.version' 
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	set -o pipefail; $(BIN)/python -m pip install -q --upgrade pip 2>&1 | { grep -v "^WARNING: Location" || true; }
	set -o pipefail; $(BIN)/python -m pip install -q -e ".[dev,train]" 2>&1 | { grep -v "^WARNING: Location" || true; }
	rm -f $(VENV)/.installed-* && touch $@

models: venv
	$(BIN)/twohr models fetch

lint: venv
	$(BIN)/ruff check .

# chromium and iproute2 from Debian where missing (scripts/test-prerequisites.sh says what to do where it cannot)
test-prerequisites:
	scripts/test-prerequisites.sh

# The documentation site (mkdocs.yml, docs/) into runs/site; strict: a warning (a broken link, a page left out of
# the nav) fails it. docs/hooks.py makes the HTTP API and bus key pages from the code as it builds.
docs: venv
	PYTHONDONTWRITEBYTECODE=1 $(BIN)/mkdocs build --strict --quiet

test: venv docs models lint test-prerequisites
	$(BIN)/python -m pytest -q --durations=15

# The whole system in containers (docker compose), with an engine started here if none answers;
# prints a SKIP line and succeeds where no engine can be started. See scripts/docker-here.sh.
compose-test: venv models
	scripts/docker-here.sh run $(BIN)/python -m pytest -q tests/test_compose_stack.py

demo: venv models
	$(BIN)/twohr demo --sequence $(DEMO_SEQUENCE) --out $(DEMO_OUT)

clean:
	rm -rf $(VENV) runs .pytest_cache .ruff_cache
