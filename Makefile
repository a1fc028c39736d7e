# cubeloc: two commands do everything on a fresh Debian/Ubuntu machine.
#   make demo   the daemon on the synthetic camera, with poses printed and an accuracy summary
#   make test   lint and the whole test suite
# Each installs what it needs (Debian packages, .venv, the project in editable mode);
# stamps in .make/ keep a second run with nothing changed down to seconds.

SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMPS := .make

# Debian packages: the Aravis typelib for the camera backend, the build deps of PyGObject,
# libusb for pyusb, and aravis-tools (arv-tool, arv-fake-gv-camera) for technicians.
DEB_PACKAGES := gir1.2-aravis-0.8 aravis-tools libgirepository1.0-dev libcairo2-dev \
                pkg-config libusb-1.0-0 python3-venv python3-dev gcc iproute2
# Tests, benchmarks and the soak run in a network namespace with only loopback (Aravis'
# GigE Vision discovery broadcasts on every interface; nothing may leave the machine).
LOOPBACK := scripts/loopback-only
# pytest workers: the suite runs on both cores of the CI machine
TEST_WORKERS ?= 2
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: all install test test-fast lint bench demo soak clean constraints

all: test

$(STAMPS)/apt: Makefile
	@mkdir -p $(STAMPS)
	@missing=$$(for p in $(DEB_PACKAGES); do dpkg-query -W -f='$${Status}\n' $$p 2>/dev/null | grep -q 'install ok installed' || echo $$p; done); \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages: $$missing"; \
	  $(SUDO) apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq $$missing; \
	fi
	@touch $@

$(BIN)/python: | $(STAMPS)/apt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

# constraints.txt: the versions the tests and benchmarks were measured with (see its header)
$(STAMPS)/install: pyproject.toml constraints.txt $(STAMPS)/apt | $(BIN)/python
	$(BIN)/python -m pip install -q -c constraints.txt -e '.[test]'
	@touch $@

install: $(STAMPS)/install

lint: install
	$(BIN)/ruff check .

# The GigE Vision fake's tests run one at a time (tests/conftest.py), mostly waiting on the
# network: alongside the rest, in a namespace of their own (its loopback is not the other's),
# their output shown when both are done.
test: lint
	@echo "$(LOOPBACK) $(BIN)/python -m pytest -q -p no:cacheprovider -m gv_fake > $(STAMPS)/gv_fake.log &"; \
	$(LOOPBACK) $(BIN)/python -m pytest -q -p no:cacheprovider -m gv_fake > $(STAMPS)/gv_fake.log 2>&1 & gv=$$!; \
	trap 'kill $$gv 2>/dev/null' INT TERM; \
	echo "$(LOOPBACK) $(BIN)/python -m pytest -q -n $(TEST_WORKERS) -m 'not gv_fake'"; \
	$(LOOPBACK) $(BIN)/python -m pytest -q -n $(TEST_WORKERS) -m 'not gv_fake'; rest=$$?; \
	wait $$gv; gv_rc=$$?; echo "-- gv_fake tests ($(STAMPS)/gv_fake.log):"; cat $(STAMPS)/gv_fake.log; \
	exit $$(( rest || gv_rc ))

# The edit-test loop: the tests of the suite under 1 s each (tests/slow_tests.txt lists the rest)
test-fast: install
	$(LOOPBACK) $(BIN)/python -m pytest -q -n $(TEST_WORKERS) -m 'not gv_fake and not slow'

bench: install
	$(LOOPBACK) $(BIN)/python -m bench

demo: install
	$(BIN)/cubeloc demo

# The daemon for 30 minutes on the pre-rendered synthetic camera at full rate: RSS, threads,
# fds, frame rate and every pose checked; writes docs/soak.md. Not part of `make test`.
soak: install
	$(LOOPBACK) nice $(BIN)/python -m bench.soak --minutes 30

# Today's releases of everything pyproject.toml asks for, frozen into constraints.txt
# (a scratch venv; .venv is left as it is until the next `make install`).
constraints: | $(STAMPS)/apt
	rm -rf $(STAMPS)/constraints-venv
	$(PYTHON) -m venv $(STAMPS)/constraints-venv
	$(STAMPS)/constraints-venv/bin/python -m pip install -q --upgrade pip
	$(STAMPS)/constraints-venv/bin/python -m pip install -q -e '.[test]'
	{ sed -n '/^#/p' constraints.txt; $(STAMPS)/constraints-venv/bin/python -m pip freeze --exclude-editable | sort -f; } > constraints.txt.new
	mv constraints.txt.new constraints.txt
	rm -rf $(STAMPS)/constraints-venv

clean:
	rm -rf $(STAMPS) $(VENV) .pytest_cache .ruff_cache
