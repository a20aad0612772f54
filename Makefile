# sync4d developer entry points.
#
#   make setup   create .venv, install the Python requirements (only when they changed), build and
#                install the Rust extension sync4d._core in release mode (only when sources changed)
#   make test    setup + lavapipe + cargo test (release) + pytest (what CI runs)
#   make test-quick  the same without the slow and reference tests (the inner loop)
#   make lint    cargo fmt --check, clippy -D warnings, ruff, the import contract (lint-imports)
#   make bench   setup + python -m sync4d bench raster $(BENCH_ARGS)
#   make fit     setup + train the embedded synthetic scene (runs/synthetic) and print test PSNR
#   make clean   drop build outputs and stamps (keeps .venv and its packages)
#
# Stamps live inside .venv, so deleting .venv resets everything.

SHELL := bash
.SHELLFLAGS := -euo pipefail -c
.DEFAULT_GOAL := test
.DELETE_ON_ERROR:
MAKEFLAGS += --no-builtin-rules

PYTHON ?= python3
VENV := .venv
VENV_ABS := $(abspath $(VENV))
VPY := $(VENV)/bin/python

# Host-side digest of the requirement set (runtime deps + `test` extra + build backend) declared in
# pyproject.toml. The install stamp is named after it: a changed set means a missing stamp, hence
# one reinstall; an unchanged pyproject.toml edit (or touch) installs nothing.
REQS_HASH := $(shell $(PYTHON) scripts/dev_requirements.py --hash)
ifeq ($(strip $(REQS_HASH)),)
$(error could not compute the requirement hash: is '$(PYTHON)' (>= 3.11) on PATH and pyproject.toml valid?)
endif
DEPS_STAMP := $(VENV)/.sync4d-deps-$(REQS_HASH).stamp
EXT_STAMP := $(VENV)/.sync4d-ext.stamp

# Everything that can change the compiled extension.
RUST_SOURCES := Cargo.toml Cargo.lock pyproject.toml \
	$(shell find rust -type f \( -name '*.rs' -o -name 'Cargo.toml' \) -not -path '*/target/*')
# If the built module was deleted by hand, rebuild even though the stamp is newer than the sources.
EXT_SO := $(wildcard sync4d/_core*.so)

# pyo3's build script re-runs (recompiling pyo3, numpy and sync4d-py) whenever PYO3_PYTHON or
# PYO3_ENVIRONMENT_SIGNATURE differ from the previous build. maturin sets both (venv interpreter,
# "cpython-3.11-64bit"); give cargo test/clippy the same values so that `maturin develop` and
# `cargo test` do not invalidate each other's artifacts in target/release on every alternation.
export PYO3_PYTHON := $(VENV_ABS)/bin/python
export PYO3_ENVIRONMENT_SIGNATURE := $(shell $(PYTHON) -c "import struct, sys; v = sys.version_info; \
	print(f'{sys.implementation.name}-{v.major}.{v.minor}-{struct.calcsize(\"P\") * 8}bit')")
ifeq ($(strip $(PYO3_ENVIRONMENT_SIGNATURE)),)
$(error could not compute PYO3_ENVIRONMENT_SIGNATURE with '$(PYTHON)')
endif

PIP_FLAGS := --disable-pip-version-check $(if $(CI),--progress-bar off --no-input)

.PHONY: setup lavapipe browser test test-quick lint bench fit clean distclean FORCE

setup: $(EXT_STAMP)

$(VPY):
	@echo ">>> creating $(VENV) with $$(command -v $(PYTHON)) ($$($(PYTHON) --version 2>&1))"
	rm -rf $(VENV)
	@if $(PYTHON) -c 'import ensurepip' 2>/dev/null; then \
		set -x; $(PYTHON) -m venv $(VENV); \
	else \
		echo ">>> $(PYTHON) has no ensurepip (Debian without python3-venv?); bootstrapping pip with the host pip"; \
		set -x; $(PYTHON) -m venv --without-pip $(VENV); \
		$(PYTHON) -m pip --python $(VPY) install $(PIP_FLAGS) pip; \
	fi
	$(VPY) -m pip --version

$(DEPS_STAMP): $(VPY) scripts/dev_requirements.py
	@echo ">>> installing Python requirements (set $(REQS_HASH))"
	$(PYTHON) scripts/dev_requirements.py > $@.tmp
	$(VPY) -m pip install $(PIP_FLAGS) -r $@.tmp
	$(PYTHON) scripts/dev_requirements.py --no-deps > $@.nodeps
	if [ -s $@.nodeps ]; then $(VPY) -m pip install $(PIP_FLAGS) --no-deps -r $@.nodeps; fi
	rm -f $@.nodeps
	rm -f $(VENV)/.sync4d-deps-*.stamp
	mv $@.tmp $@

$(EXT_STAMP): $(DEPS_STAMP) $(RUST_SOURCES) $(if $(EXT_SO),,FORCE)
	@echo ">>> building sync4d._core (release) and installing it into $(VENV)"
	VIRTUAL_ENV=$(VENV_ABS) PATH="$(VENV_ABS)/bin:$$PATH" $(VENV)/bin/maturin develop --release
	@# Import from outside the tree: proves the editable install (.pth) works, not just the cwd.
	cd / && $(VENV_ABS)/bin/python -c 'import sync4d._core'
	touch $@

FORCE:

# lavapipe (Mesa's CPU Vulkan driver), so the wgpu tests run without a GPU: installed from Debian's
# packages when missing (as root, or through sudo). In CI a failed install fails the build; elsewhere
# the wgpu tests then skip with a message (they use any real GPU adapter there is).
lavapipe:
	@if ls /usr/share/vulkan/icd.d/lvp_icd*.json >/dev/null 2>&1 && \
		{ ldconfig -p 2>/dev/null | grep -q 'libvulkan.so.1'; }; then \
		echo ">>> lavapipe: present"; \
	elif command -v apt-get >/dev/null; then \
		echo ">>> installing lavapipe (mesa-vulkan-drivers, libvulkan1) for the wgpu tests"; \
		sudo=""; [ "$$(id -u)" = 0 ] || sudo=sudo; \
		$$sudo apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $$sudo apt-get install -y -qq mesa-vulkan-drivers libvulkan1 \
			|| { echo "lavapipe install failed"; [ -z "$(CI)" ]; }; \
	else \
		echo ">>> no apt-get: install a Vulkan driver to run the wgpu tests (they skip otherwise)"; \
		[ -z "$(CI)" ]; \
	fi

# The viewer's browser test drives Debian's Chromium through its chromedriver: installed when
# missing, like lavapipe (a failed install fails CI; elsewhere the browser test skips).
browser:
	@if command -v chromium >/dev/null && command -v chromedriver >/dev/null; then \
		echo ">>> chromium: present"; \
	elif command -v apt-get >/dev/null; then \
		echo ">>> installing chromium and chromium-driver for the viewer's browser test"; \
		sudo=""; [ "$$(id -u)" = 0 ] || sudo=sudo; \
		$$sudo apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $$sudo apt-get install -y -qq chromium chromium-driver \
			|| { echo "chromium install failed"; [ -z "$(CI)" ]; }; \
	else \
		echo ">>> no apt-get: install Chromium and chromedriver to run the browser test"; \
		[ -z "$(CI)" ]; \
	fi

# Deterministic thread counts for the test suite (2-core CI machines); exported to every recipe
# this target runs, including its prerequisites.
test test-quick: export OMP_NUM_THREADS := 2
test test-quick: export MKL_NUM_THREADS := 2
test test-quick: export RAYON_NUM_THREADS := 2
# In CI the wgpu tests must find an adapter (lavapipe); Mesa wants a runtime dir.
test test-quick: export SYNC4D_REQUIRE_GPU := $(if $(CI),1,0)
test test-quick: export SYNC4D_REQUIRE_BROWSER := $(if $(CI),1,0)
test test-quick: export XDG_RUNTIME_DIR := $(or $(XDG_RUNTIME_DIR),/tmp)
test: setup lavapipe browser
	cargo test --workspace --release
	$(VPY) -m pytest -q

# The inner loop: everything but the tests marked slow (each over 30 s) and the gsplat
# reference comparisons.
test-quick: setup lavapipe browser
	cargo test --workspace --release
	$(VPY) -m pytest -q -m "not slow and not reference"

lint: $(DEPS_STAMP)
	cargo fmt --all --check
	cargo clippy --workspace --all-targets -- -D warnings
	$(VENV)/bin/ruff check .
	$(VENV)/bin/lint-imports

BENCH_ARGS ?=
bench: setup
	$(VPY) -m sync4d bench raster $(BENCH_ARGS)

FIT_ARGS ?=
fit: setup
	$(VPY) -m sync4d fit --out runs/synthetic --force $(FIT_ARGS)

clean:
	rm -f $(EXT_STAMP) sync4d/_core*.so
	cargo clean

distclean: clean
	rm -rf $(VENV)
