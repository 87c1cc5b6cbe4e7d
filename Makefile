# selfseg: two commands on a fresh Debian/Ubuntu machine with Python 3.11.
#   make demo   install everything, then run the demo on the demo preset
#   make test   install everything, then run the whole test suite (what CI runs)
SHELL := /bin/bash
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
DEMO   := runs/demo

.PHONY: demo test install leaderboards clean

install: $(STAMP)

$(STAMP): pyproject.toml scripts/install_system_deps.sh
	bash scripts/install_system_deps.sh
	@$(PYTHON) -c 'import sys; assert sys.version_info[:2] == (3, 11), "selfseg needs Python 3.11 (bpy 5.0.1); set PYTHON=/path/to/python3.11"'
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	touch $@

demo: $(STAMP)
	bash scripts/demo.sh $(DEMO)

# The committed leaderboards/ from a finished demo's results (RESULTS=... for another run's, e.g.
# runs/calibrated/results): `make demo` itself writes only under runs/demo.
RESULTS ?= $(DEMO)/results
leaderboards: $(STAMP)
	$(PY) -m selfseg.eval.leaderboard --results $(RESULTS) --out leaderboards/

# The suite runs as on a fresh machine: an empty HOME (no caches, no matplotlib font cache), MPLCONFIGDIR unset;
# in two pytest-xdist workers, one per core of the CI machine (serially the suite keeps 0.6 of the 2 cores busy).
test: $(STAMP)
	home=$$(mktemp -d) && trap 'rm -rf "$$home"' EXIT && env -u MPLCONFIGDIR HOME="$$home" $(PY) -m pytest -q -n 2

clean:
	rm -rf $(VENV) runs
