# Two commands set up and run everything on a fresh Debian 12 machine:
#   make demo   - system packages, .venv, the project, then the demo on the built-in patient
#   make test   - the same set-up, then the linters (make lint: ruff and mypy) and the test suite
# Each step is skipped when its result is already there, so a second run starts at once.

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
# Debian packages: libsystemd-dev and pkg-config build systemd-python; pocl-opencl-icd is a
# second CPU OpenCL whose compiler targets processors newer than the LLVM of the PoCL wheel
# (which refuses to build anything there: 'unknown target CPU generic'); dicom3tools gives
# dciodvfy, which checks exported dose reports; systemd gives systemd-analyze for unit checks;
# gcc and linux-libc-dev let a test check the framebuffer structs against <linux/fb.h>;
# alsa-utils gives aplay, which sounds the fluoroscopy-time alarm; dcmtk gives dsrdump and
# dcentvfy, which check a session's dose report and images together, and orthanc is the real
# PACS the DICOM sending tests store into, on loopback in a network namespace of their own
# (iproute2 brings its lo up); openssl makes the certificates of the DICOM-over-TLS test;
# grub-common gives Debian's grub.d scripts, grub-mkpasswd-pbkdf2 and grub-script-check, which
# make and parse the locked boot menu provisioning writes; clang-15 (PoCL's own compiler) also
# compiles drr.cl for GPU targets in a test, where no GPU is.
APT_PACKAGES := libsystemd-dev pkg-config pocl-opencl-icd clang-15 dicom3tools systemd python3-venv gcc linux-libc-dev alsa-utils dcmtk orthanc iproute2 openssl grub-common
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: demo test lint setup system-packages bench mutation mutation-console mutation-display mutation-dose \
	mutation-records mutation-geometry clean

demo: setup
	$(BIN)/fluorosim demo

# Two pytest workers (pytest-xdist): much of the suite waits on daemons, receivers and their
# clocks rather than computing, so a second worker fills those waits on a two-core machine (the
# whole suite on a shared two-core machine, load average 7-8: 790 s in one process, 481 s in two).
# A test that times the daemon (stop within 2 s of SIGTERM) has less margin beside a second worker
# on a loaded machine; TEST_WORKERS=0 runs everything in one process.
TEST_WORKERS ?= 2

test: lint
	$(BIN)/python -m pytest -n $(TEST_WORKERS)

# Settings for both are in pyproject.toml ([tool.ruff], [tool.mypy]).
lint: setup
	$(BIN)/ruff check .
	$(BIN)/mypy

setup: system-packages $(VENV)/.installed

system-packages:
	@missing=$$(for p in $(APT_PACKAGES); do dpkg-query -W -f='$${Status}\n' $$p 2>/dev/null | grep -q '^install ok installed' || echo $$p; done); \
	if [ -n "$$missing" ]; then \
		echo "Installing system packages:" $$missing; \
		$(SUDO) apt-get update -q && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -q $$missing; \
	fi

$(VENV)/.installed: pyproject.toml
	[ -x $(BIN)/python ] || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test,bench]'
	touch $@

# Mutation testing of the modules where a silent bug costs most ([tool.mutmut] in pyproject.toml):
# slow (about a second a mutant, under an hour in all at one child), so not part of `make test`.
# `make mutation` runs every group of tests/mutation_module.py in turn (console, display, dose,
# records, geometry), each with only its own tests, prints each group's score per module and
# fails on a module under 90 % or a surviving mutant not justified in
# tests/mutation-equivalent.txt; `make mutation-GROUP` runs one group. mutmut gets a venv of its
# own: it reads a private attribute pytest 9 no longer has, and its click pin conflicts with the
# LRS's (ralph-malph) in the test venv. One mutant at a time by default (MUTATION_CHILDREN=2 on a
# quiet machine); which functions count: tests/mutation_score.py's TARGETS.
MVENV := .venv-mutation
MUTATION_CHILDREN ?= 1

$(MVENV)/.installed: pyproject.toml
	[ -x $(MVENV)/bin/python ] || $(PYTHON) -m venv $(MVENV)
	$(MVENV)/bin/python -m pip install -q --upgrade pip
	$(MVENV)/bin/python -m pip install -q -e '.[mutation]'
	touch $@

mutation: system-packages $(MVENV)/.installed
	$(MVENV)/bin/python tests/mutation_module.py all $(MUTATION_CHILDREN)

# One group: the console state machine (about 1,040 mutants); the compositor and its text; the
# dose model and the console's readout; the RDSR writer; the geometry, the renderer's pixel
# geometry and calibration acceptance.
mutation-console mutation-display mutation-dose mutation-records mutation-geometry: system-packages $(MVENV)/.installed
	$(MVENV)/bin/python tests/mutation_module.py $(@:mutation-%=%) $(MUTATION_CHILDREN)

bench: setup
	$(BIN)/fluorosim bench all

clean:
	rm -rf $(VENV) $(MVENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache

# The appliance's pinned, hashed dependencies (provisioning/requirements.lock), from pyproject.toml.
.PHONY: lock
lock: setup
	$(BIN)/python -m pip lock . -o .pylock.toml
	$(BIN)/python provisioning/lock_requirements.py .pylock.toml provisioning/requirements.lock
	rm -f .pylock.toml
