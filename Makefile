# Set-up and the two commands of the README. Everything a fresh machine needs is installed here.
PY ?= python3
VENV := .venv
STAMP := $(VENV)/.installed

.PHONY: demo test lint setup

setup: $(STAMP)

$(STAMP): pyproject.toml setup.py omni_sfm/_buffers.h omni_sfm/estimate/_lines.c \
		omni_sfm/lines/_edges.c
	@# Open3D's wheel needs libusb-1.0 at import time (Debian package libusb-1.0-0);
	@# tests/test_view.py opens the HTML viewer in a headless browser (Debian package chromium);
	@# the line adjustment's and the line extractor's loops (omni_sfm/estimate/_lines.c,
	@# omni_sfm/lines/_edges.c) are compiled by the install:
	@# a C compiler (gcc) and Python's headers (python3-dev where Python is Debian's own)
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || ! command -v chromium >/dev/null 2>&1 \
	    || ! command -v cc >/dev/null 2>&1 \
	    || [ ! -f "$$($(PY) -c 'import sysconfig; print(sysconfig.get_paths()["include"])')/Python.h" ]; then \
	  PKGS="libusb-1.0-0 chromium gcc"; \
	  case "$$($(PY) -c 'import sys; print(sys.prefix)')" in /usr) PKGS="$$PKGS python3-dev";; esac; \
	  echo "installing Debian packages $$PKGS"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$PKGS; \
	fi
	$(PY) -m venv $(VENV)
	$(VENV)/bin/python -m pip install -q --upgrade pip
	$(VENV)/bin/python -m pip install -q -e '.[dev,compare]'
	@touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/omni-sfm demo

test: $(STAMP)
	@# pytest exits 5 when it collected no test; that is not a failure of the suite. One test
	@# process per core (pytest-xdist), one test at a time to each, the slow tests first
	@# (tests/conftest.py); renders and folders several tests share are made once, by the first
	@# process that needs them (1,112 tests in 250-302 s on 2 cores).
	OPENBLAS_NUM_THREADS=1 $(VENV)/bin/python -m pytest -q -n auto --maxschedchunk 1; rc=$$?; if [ $$rc -eq 5 ]; then rc=0; fi; exit $$rc

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy
