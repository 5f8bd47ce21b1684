# The two commands of the README: `make demo` (the main job) and `make test` (the test suite).
# Each creates the environment on a fresh machine (system libraries, a virtualenv in .venv, the pinned
# packages of requirements.lock) and is idempotent: a second run installs nothing.

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Debian packages: what the wheels need at import time (open3d links libusb-1.0), and the browser the report
# test renders report.html in (headless).
SYSTEM_PACKAGES := libusb-1.0-0 chromium

.PHONY: all env system-deps demo test fuzz lint bench lock clean

all: demo

system-deps:
	@missing=""; for p in $(SYSTEM_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  if [ "$$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing; \
	fi

$(STAMP): requirements.lock pyproject.toml
	@$(MAKE) --no-print-directory system-deps
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.lock
	@touch $(STAMP)

# numba's on-disk cache (__pycache__/*.nbi, *.nbc beside each compiled module), filled by the pipeline on a
# short simulated run (pipeline/warmup.py) so that the first `make demo` does not compile: once after each
# install, and again after an edit of the compiled modules or of the code that calls them (an unchanged
# function loads from the cache, so a re-warm costs only the short run). A failed warm-up does not stop
# `make test` (numba then compiles on first use); the next `make` tries again.
WARM := $(VENV)/.numba-warm
WARM_SOURCES := $(wildcard mapping/*.py mapping/tiling/*.py slam/*.py datasets/*.py datasets/ros/*.py \
  datasets/simulation/*.py pipeline/*.py pipeline/default.yaml)

# Numba keys a cached function on its own module's source only, so an edit of a function it inlines from
# another module (e.g. mapping/index.py into mapping/core.py) would leave stale machine code: an edit of a
# package's modules drops that package's cache first.
$(WARM): $(STAMP) $(WARM_SOURCES)
	@for pkg in mapping slam datasets; do \
	  if echo " $? " | grep -q " $$pkg/"; then find $$pkg -name '*.nb[ic]' -path '*__pycache__*' -delete; fi; \
	done
	@echo "compiling the numba cores once (pipeline/warmup.py)"
	@if $(PY) -m pipeline.warmup; then touch $(WARM); \
	  else echo "warm-up failed: numba will compile on first use"; fi

env: system-deps $(STAMP) $(WARM)

# The demo's folder is its own output: a second `make demo` replaces it.
demo: env
	$(PY) run.py demo --overwrite

test: env
	$(PY) -m pytest -q

# The long profile of the fuzzing harness (tests/fuzz, 15-25 minutes): random cases, thousands per property;
# `make test` runs its short deterministic profile.
fuzz: env
	GPOM_FUZZ_PROFILE=long $(PY) -m pytest -q tests/fuzz --hypothesis-show-statistics

lint: env
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

bench: env
	$(PY) run.py bench

# Re-pin the whole environment from pyproject.toml's direct pins.
lock:
	rm -rf /tmp/gpom-lock-venv && $(PYTHON) -m venv /tmp/gpom-lock-venv
	/tmp/gpom-lock-venv/bin/python -m pip install --quiet ".[dev]" && \
	  /tmp/gpom-lock-venv/bin/python -m pip freeze --exclude gpom > requirements.lock.tmp
	@{ echo "# Full pinned environment (pip freeze of a fresh install of pyproject.toml [project] + [dev])."; \
	   echo "# Regenerate with \`make lock\`; installed by \`make env\` (called by \`make demo\` and \`make test\`)."; \
	   cat requirements.lock.tmp; } > requirements.lock && rm requirements.lock.tmp

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache
