# Developer entry points for h2o_slam. The README's two commands are `make demo` and
# `make test`; CI runs `make test` through .ci/run.

SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := help

VENV := .venv
PY := $(VENV)/bin/python
# Evaluated only when the venv has to be created.
BOOTSTRAP_PYTHON = $(shell command -v python3.11 || command -v python3)
DEV_STAMP := $(VENV)/.h2o-dev-installed
BENCH_STAMP := $(VENV)/.h2o-bench-installed
KERNEL_STAMP := $(VENV)/.h2o-kernels-warm
OUT := out/demo

# DDS stays on this machine: Fast DDS with the loopback-only profile (shared memory + UDP on
# 127.0.0.1, unicast discovery, no multicast). The profile alone decides; the ROS discovery
# variables that would override it are removed from the environment of every recipe.
export RMW_IMPLEMENTATION := rmw_fastrtps_cpp
export FASTRTPS_DEFAULT_PROFILES_FILE := $(CURDIR)/config/fastdds_localhost.xml
export FASTDDS_DEFAULT_PROFILES_FILE := $(CURDIR)/config/fastdds_localhost.xml
unexport ROS_LOCALHOST_ONLY ROS_AUTOMATIC_DISCOVERY_RANGE ROS_STATIC_PEERS

.PHONY: help venv demo test bench doc-images clean

help:
	@echo "make demo   h2o-demo: simulated drive -> bag -> replay through both nodes -> ATE table"
	@echo "make test   ruff, mypy and pytest (what CI runs)"
	@echo "make bench  benchmarks against reference solvers (installs requirements-bench.txt; H2O_POSEGRAPHS=DIR: the public pose graphs, bench/README.md)"
	@echo "make doc-images  copy the plots of the last make demo (out/demo/*.png) into doc/images/"
	@echo "make venv   create/update .venv (reruns when a requirements file, setup.py or tools/tf2_msgs changes) and compile the solver kernels into the cache"
	@echo "make clean  remove build/, install/, log/ and out/"

venv: $(DEV_STAMP) $(KERNEL_STAMP)

# tf2_msgs (TFMessage for /tf) is not on PyPI: tools/build_tf2_msgs.sh generates and compiles
# it from tools/tf2_msgs with the rosidl generators of the ROS wheels (a few seconds; no-op when
# already built).
TF2_MSGS_SRC := tools/build_tf2_msgs.sh tools/rosidl_generate.py tools/tf2_msgs/package.xml \
  $(wildcard tools/tf2_msgs/msg/*.msg)

# The editable install maps each top-level package when it is made: a new package (a new
# top-level __init__.py) needs it made again, or imports from outside the checkout fail.
$(DEV_STAMP): requirements.txt requirements-dev.txt setup.py setup.cfg pyproject.toml \
  $(wildcard */__init__.py) $(TF2_MSGS_SRC)
	@if [ ! -x $(PY) ]; then \
	  echo "creating $(VENV) with $(BOOTSTRAP_PYTHON)"; \
	  $(BOOTSTRAP_PYTHON) -m venv $(VENV); \
	fi
	$(PY) -m pip install --quiet -r requirements-dev.txt
	bash tools/build_tf2_msgs.sh $(VENV)
	$(PY) -m pip install --quiet -e .
	@touch $@

# The solver's compiled kernels, loaded or compiled into the user's cache now (a minute or
# more on two cores when the kernel sources changed; a second otherwise), so that no command,
# node or test compiles on first use.
$(KERNEL_STAMP): $(DEV_STAMP) $(wildcard h2o_slam/core/*.py)
	$(PY) -m h2o_slam.core.warmup
	@touch $@

$(BENCH_STAMP): $(DEV_STAMP) $(KERNEL_STAMP) requirements-bench.txt
	$(PY) -m pip install --quiet -r requirements-bench.txt
	@touch $@

demo: venv
	@rm -rf $(OUT)
	$(VENV)/bin/h2o-demo --output $(OUT)

# Runs all three checks even when one fails, then fails if any did. pytest's exit code 5
# (no tests collected) is a failure here: a green run must have run tests.
test: venv
	@failed=""; \
	echo "== ruff check ."; $(PY) -m ruff check . || failed="$$failed ruff"; \
	echo "== mypy"; $(PY) -m mypy || failed="$$failed mypy"; \
	echo "== pytest"; rc=0; $(PY) -m pytest -q || rc=$$?; \
	if [ $$rc -eq 5 ]; then \
	  echo "make test: pytest collected no tests; failing" >&2; failed="$$failed pytest(no-tests)"; \
	elif [ $$rc -ne 0 ]; then failed="$$failed pytest"; fi; \
	if [ -n "$$failed" ]; then echo "make test: FAILED:$$failed" >&2; exit 1; fi

bench: $(BENCH_STAMP)
	$(PY) bench/solvers.py
	$(PY) bench/lago.py
	$(PY) bench/online.py

# The README's pictures: the three plots h2o-demo draws of both runs (h2o_slam.app.cli.demo.PLOTS).
DOC_IMAGES := trajectories.png chi2.png callback_times.png

doc-images:
	@for f in $(DOC_IMAGES); do \
	  test -f $(OUT)/$$f || { echo "make doc-images: no $(OUT)/$$f; run make demo first" >&2; exit 1; }; \
	done
	mkdir -p doc/images
	cd $(OUT) && cp $(DOC_IMAGES) $(CURDIR)/doc/images/

clean:
	rm -rf build install log out
