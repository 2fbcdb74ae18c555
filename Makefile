# The two commands: `make run` (the main job) and `make test`. Both create the
# virtual environment on first use and re-install when pyproject.toml changes.

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
MAVPROXY := $(BIN)/mavproxy.py

.PHONY: venv run test bench bench-outputs soak faults

venv: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -e '.[dev]'
	$(BIN)/python -m onboard.app.warm
	touch $@

# The main job: the onboard service on a synthetic 20 s orbit (exact ground
# truth, no shared data or hardware needed), generated on the fly and replayed
# at real-time pace, MAVLink to 127.0.0.1:14550 and zenoh on 127.0.0.1:7447.
run: $(STAMP)
	$(BIN)/nislam run --sim circle --seconds 20 --config config/demo.toml --out results/run_sim_circle

# MAVProxy is the receiving peer of one test (tests/test_mavlink_mavproxy.py).
# Installed without its dependencies: it requires opencv-python, which would
# overwrite our opencv-python-headless (both install the cv2 module). Headless
# (--daemon --non-interactive) it needs only pymavlink, pyserial and numpy,
# which pyproject.toml already brings.
$(MAVPROXY): $(STAMP)
	$(BIN)/python -m pip install --no-deps 'MAVProxy==1.8.75'
	touch $@

# The architecture's import contracts (pyproject.toml [tool.importlinter]), then the tests.
test: $(STAMP) $(MAVPROXY)
	$(BIN)/lint-imports
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/nislam bench

# MAVLink send rate and jitter, per-frame cost of the outputs in the loop.
bench-outputs: $(STAMP)
	$(BIN)/python scripts/bench_outputs.py

# The service replaying a looped synthetic flight for 10 minutes: RSS, latency
# percentiles over time, dropped frames (scripts/soak.py --help).
soak: $(STAMP)
	$(BIN)/python scripts/soak.py --minutes 10

# The fault matrix: each fault injected into the real drivers and the service,
# then cleared; the table goes into docs/reliability.md (tests/fault_matrix.py).
faults: $(STAMP)
	$(BIN)/python scripts/fault_matrix.py
