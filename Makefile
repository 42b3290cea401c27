# The two commands of the README. Each creates .venv and installs cellcal with its
# dev extras from PyPI on first use (and again when pyproject.toml changes).
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo demo-identify test test-fast bench clean

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV) || python3 -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

# the whole product on the simulated cell: fakes, daemon, start button, tcp-laser, write-back
demo: $(STAMP)
	$(BIN)/cellcal demo --cell sim-net --routine tcp-laser

# the kinematic identification on a simulated tracker campaign
demo-identify: $(STAMP)
	$(BIN)/cellcal sim-campaign --robot ur10e --poses 60 --out out/demo

# two workers, a test file each at a time (module fixtures such as a running sim-net stay
# in one worker): most end-to-end cases wait on simulated devices that run in real time
test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile -m "not slow"

bench: $(STAMP)
	$(BIN)/python bench/identify_bench.py

clean:
	rm -rf $(VENV) out .pytest_cache
