# The two entry points of the README. Both set up a virtual environment in .venv first.
PY ?= python3
VENV := .venv
SHELL := /bin/bash
.SHELLFLAGS := -o pipefail -c
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup system-deps demo test

# Debian packages: libusb for `import open3d` (ray-casting renderer), chromium for the viewer's browser test,
# docker-compose to validate docker/compose.yaml (no engine needed), openssl and iproute2 for the deployment tests.
system-deps:
	@if ! ldconfig -p | grep -q libusb-1.0 || ! command -v chromium >/dev/null || ! command -v docker-compose >/dev/null \
	    || ! command -v openssl >/dev/null || ! command -v ip >/dev/null; then \
	  if command -v apt-get >/dev/null && [ "$$(id -u)" = 0 ]; then \
	    echo "[setup] installing Debian packages libusb-1.0-0 chromium docker-compose openssl iproute2"; \
	    (apt-get install -y -q libusb-1.0-0 chromium docker-compose openssl iproute2 >/dev/null 2>&1 || \
	     (apt-get update -q >/dev/null 2>&1 && apt-get install -y -q libusb-1.0-0 chromium docker-compose openssl iproute2 >/dev/null)); \
	  else echo "please install Debian packages libusb-1.0-0 chromium docker-compose openssl iproute2"; fi; fi

$(STAMP): pyproject.toml
	@echo "[setup] creating $(VENV) and installing sigmaslam with its dependencies (1-3 min on a fresh machine)"
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --no-cache-dir --upgrade pip
	@# --no-cache-dir: the venv is ~2.6 GB; a wheel cache beside it would double what a small CI disk must hold
	@# pip says nothing while it unpacks (torch alone takes ~30 s): a line every 15 s shows it is alive
	@( while sleep 15; do echo "[setup] still installing ($$SECONDS s)"; done ) & beat=$$!; \
	PYTHONUNBUFFERED=1 $(BIN)/pip install --no-cache-dir --progress-bar off -e '.[dev]' \
	  | awk '/^(Collecting|Installing|Successfully)/ { print substr($$0, 1, 160); fflush() }'; \
	rc=$$?; kill $$beat; exit $$rc
	touch $(STAMP)

setup: system-deps $(STAMP)

# the demo prints the set-up's wall time among its phases
demo:
	@t0=$$(date +%s%N); $(MAKE) --no-print-directory setup && \
	$(BIN)/sigmaslam demo --setup-s $$(( ($$(date +%s%N) - t0) / 1000000000 ))

# everything CI runs (.ci/run): lint, then every tier (unit, service, e2e in its reduced form; tests/README.md):
# all but the live pipelines on both cores (pytest-xdist), then the live pipelines (marker processes) one at a time
test: setup
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q -n 2 -m "not processes"
	$(BIN)/python -m pytest -q -m processes
