# The two commands of the README. Each creates .venv and installs cellcal with its dev
# extras on first use, at the exact versions of requirements.lock (and again when
# pyproject.toml or the lock file changes). `make lock` moves the lock on purpose.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
LOCK := requirements.lock
# -qq: errors only. This machine's pip configuration names package indexes that do not all
# exist, and pip warns about each one on every call; a failing install still says why.
PIP := $(BIN)/python -m pip -qq

.PHONY: demo demo-identify test test-fast bench wheel lock clean chromium mosquitto

$(STAMP): pyproject.toml $(LOCK)
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV) || python3 -m venv $(VENV)
	$(PIP) install -c $(LOCK) --upgrade pip
	$(PIP) install -c $(LOCK) -e '.[dev,ur]'
	@# the Franka extra (pylibfranka, and franky-sim for the sim-franka cell) where its wheels install on this
	@# machine; where they do not, the Franka tests skip and say what is missing
	@$(PIP) install -c $(LOCK) -e '.[dev,ur,franka]' || \
	  echo "the franka extra (pylibfranka, franky-sim) could not be installed: the sim-franka tests will skip"
	@touch $(STAMP)

# the whole product on the simulated cell: fakes, daemon, start button, tcp-laser, write-back
demo: $(STAMP)
	$(BIN)/cellcal demo --cell sim-net --routine tcp-laser

# the kinematic identification on a simulated tracker campaign
demo-identify: $(STAMP)
	$(BIN)/cellcal sim-campaign --robot ur10e --poses 60 --out out/demo

# two workers, a test file each at a time (module fixtures such as a running sim-net stay
# in one worker): the end-to-end cases run the networked fakes on a clock 3x the wall's
# (tests/support/daemon_harness.py), the in-process cell as fast as it computes; the slowest
# cases are listed at the end. Then the Franka cell's end-to-end cases on their own: franky-sim's
# physics and libfranka's 1 kHz loop take most of both cores at twice real time, and beside the
# other worker they starved its fakes' wall-clock handshakes (tests/e2e/test_franka_cell.py)
FRANKA_E2E := tests/e2e/test_franka_cell.py
test: $(STAMP) chromium mosquitto
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --durations=15 --deselect $(FRANKA_E2E)
	$(BIN)/python -m pytest -q --durations=5 $(FRANKA_E2E)

# $(call debian_package,PACKAGE,WHO): Debian's PACKAGE (its program of the same name, on PATH or in
# /usr/sbin), installed when it is missing and this is root with apt-get, for WHO (the tests that need
# it); a no-op once it is there. It never fails the build: where it cannot be installed those tests
# skip and say what is missing. `apt-get update` only when the first try finds no package.
define debian_package
	@command -v $(1) >/dev/null 2>&1 || test -x /usr/sbin/$(1) || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "installing Debian's $(1) for $(2) (apt-get)"; \
	    export DEBIAN_FRONTEND=noninteractive; \
	    { apt-get install -y -qq --no-install-recommends $(1) >/dev/null 2>&1 || \
	      { apt-get update -qq >/dev/null 2>&1 && \
	        apt-get install -y -qq --no-install-recommends $(1) >/dev/null 2>&1; }; } || \
	    echo "$(1) could not be installed (apt-get failed): $(2) will skip"; \
	  else \
	    echo "$(1) is not installed (needs root and apt-get to install it): $(2) will skip"; \
	  fi; }
endef

# Debian's headless-capable Chromium for the status page's browser test (tests/e2e/test_status_page_browser.py)
chromium:
	$(call debian_package,chromium,the browser test)

# Debian's Mosquitto for the plant tests (tests/e2e/test_plant_*.py: a real MQTT broker, started by the
# tests on a loopback port with their own configuration; the package's own service, where one starts,
# is not used)
mosquitto:
	$(call debian_package,mosquitto,the plant tests)

test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile -m "not slow"

bench: $(STAMP)
	$(BIN)/python bench/identify_bench.py

# dist/cellcal-VERSION-py3-none-any.whl, for the cell PC (docs/integrator.md: Installing on the cell PC).
# Built with the lock file's setuptools; build/ goes first, as setuptools would otherwise
# pack modules an earlier build left there.
wheel: $(STAMP)
	rm -rf build
	$(PIP) wheel --no-deps --no-build-isolation --check-build-dependencies -w dist .
	@rm -rf build
	@ls -t dist/cellcal-*-py3-none-any.whl | head -n 1

# Regenerate $(LOCK) on purpose: the newest releases pyproject.toml allows, installed into
# a fresh venv without constraints, frozen. Then `make test`, and commit both.
lock:
	@set -e; tmp=$$(mktemp -d); trap 'rm -rf "$$tmp"' EXIT; \
	$(PYTHON) -m venv "$$tmp/venv"; \
	"$$tmp/venv/bin/python" -m pip -qq install --upgrade pip; \
	"$$tmp/venv/bin/python" -m pip -qq install -e '.[dev,ur,franka]'; \
	{ sed -n '/^#/!q;p' $(LOCK) 2>/dev/null || true; } > "$$tmp/lock"; \
	"$$tmp/venv/bin/python" -m pip freeze --all --exclude-editable >> "$$tmp/lock"; \
	mv "$$tmp/lock" $(LOCK); \
	echo "$(LOCK): $$(grep -cv '^#' $(LOCK)) pinned; run make test, then commit it"

clean:
	rm -rf $(VENV) out .pytest_cache build
