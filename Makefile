# Set-up and the two commands the README promises: `make demo` and `make test`.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
INSTALLED := $(VENV)/.installed
# Warp's kernel cache: the checkout's unless one is given, an empty one being none (which
# `?=` would keep, and Warp take for the working folder).
ifeq ($(strip $(WARP_CACHE_PATH)),)
override WARP_CACHE_PATH := $(CURDIR)/.cache/warp
endif
export WARP_CACHE_PATH

.PHONY: demo test lint setup llvm

# Renders the rosewood bunny (scenes/bunny_wood.xml) to out/bunny.png, statistics in out/bunny.png.json.
demo: setup
	$(VENV)/bin/warptex render scenes/bunny_wood.xml -o out/bunny.png --spp 16 --res 256x256

test: setup
	$(PY) -m pytest -q

lint: setup
	$(VENV)/bin/ruff check .

setup: llvm $(INSTALLED)

# Mitsuba's LLVM variants need libLLVM >= 16 (see warptex/llvm.py). Install Debian's libllvm19
# when none is present and we may; otherwise warptex falls back to scalar rendering by itself.
llvm:
	@if ! "$(PYTHON)" warptex/llvm.py >/dev/null && [ "$$(id -u)" = 0 ] \
		&& command -v apt-get >/dev/null; then \
		echo "installing libllvm19 for Mitsuba's LLVM variants"; \
		(apt-get update -qq && apt-get install -y -qq libllvm19) \
			|| echo "warning: could not install libllvm19; Mitsuba will use scalar_rgb"; \
	fi

$(INSTALLED): pyproject.toml
	# A venv that fails half-way (Debian without python3-venv) leaves a python without pip,
	# which the next run would take for a venv: removed, the next run makes it again.
	test -x $(PY) || "$(PYTHON)" -m venv $(VENV) || { rm -rf $(VENV); exit 1; }
	$(PY) -m pip install -q -e '.[dev]'
	touch $@
