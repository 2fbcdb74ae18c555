# The two commands: `make run` (the main job) and `make test`. Both create the
# virtual environment on first use and re-install when pyproject.toml changes.

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
MAVPROXY := $(BIN)/mavproxy.py

.PHONY: venv run test bench bench-outputs

venv: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -e '.[dev]'
	touch $@

# The main job: fly a synthetic 20 s orbit (exact ground truth, no shared data
# needed) into results/sim_circle, then replay it with the NI-SLAM tracker.
run: $(STAMP)
	$(BIN)/nislam sim circle --seconds 20 --out results/sim_circle
	$(BIN)/nislam replay results/sim_circle --out results/sim_circle/replay

# MAVProxy is the receiving peer of one test (tests/test_mavlink_mavproxy.py).
# Installed without its dependencies: it requires opencv-python, which would
# overwrite our opencv-python-headless (both install the cv2 module). Headless
# (--daemon --non-interactive) it needs only pymavlink, pyserial and numpy,
# which pyproject.toml already brings.
$(MAVPROXY): $(STAMP)
	$(BIN)/python -m pip install --no-deps 'MAVProxy==1.8.75'
	touch $@

test: $(STAMP) $(MAVPROXY)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/nislam bench

# MAVLink send rate and jitter, per-frame cost of the outputs in the loop.
bench-outputs: $(STAMP)
	$(BIN)/python scripts/bench_outputs.py
