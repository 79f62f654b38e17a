# The two commands a newcomer needs:  make run   and   make test
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
ARGS ?=

.PHONY: run test test-fast install lint fmt docs bench-transport clean

$(STAMP): pyproject.toml
	@test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q -e '.[dev]'
	@touch $(STAMP)

install: $(STAMP)

# Full local stack with embedded defaults (Zenoh router inside the launcher; nothing external).
run: $(STAMP)
	$(VENV)/bin/mea run --task block_pull --demos 2 --env-steps 20000 $(ARGS)

# Lint, architecture contracts, then the whole test suite.
test: $(STAMP) lint
	$(PY) -m pytest $(ARGS)

# The inner loop: unit, contract and integration tests less the ones marked slow (under 3 minutes on
# an idle 2-core machine); CI runs `make test`, everything.
test-fast: $(STAMP)
	$(PY) -m pytest tests/unit tests/contract tests/integration -m "not slow" $(ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/lint-imports
	$(PY) -m proto.docs --check

fmt: $(STAMP)
	$(VENV)/bin/ruff check --fix .
	$(VENV)/bin/ruff format .

docs: $(STAMP)
	$(PY) -m proto.docs

bench-transport: $(STAMP)
	$(VENV)/bin/mea bench transport $(ARGS)

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .hypothesis build dist *.egg-info
