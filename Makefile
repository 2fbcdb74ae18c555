# The two commands: `make run` (the main job) and `make test`. Both create the
# virtual environment on first use and re-install when pyproject.toml changes.

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: venv run test bench

venv: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -e '.[dev]'
	touch $@

# Until the synthetic-flight demo exists, the main job replays the shared TUM
# sequence that lives beside the checkout.
run: $(STAMP)
	$(BIN)/nislam replay ../shared/data/tum_fr1_rpy --out results/tum_fr1_rpy

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/nislam bench
