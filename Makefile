# sep: build, test and demo entry points.  `make test` is the one test command.
#
#   make venv    create .venv (python3.11, else python3), install requirements.txt and the
#                example plant package (examples/burgers)
#   make build   colcon build of ros_ws/ (the ros2-run layout under ros_ws/install)
#   make test    build, then pytest over tests/ and every <pkg>/test/ that exists
#   make demo    build, then run the `demo` executable from the install space
#   make bench   run every bench/*.py with the venv python (bench_scale.py as --quick)
#   make bench-scale  bench/bench_scale.py: the scaling table across plants and grids (long;
#                BENCH_SCALE_ARGS=--quick for the small rows)
#   make fmu-rod build the example FMU examples/fmu_rod/rod.fmu from its C source (needs cc/gcc;
#                FMU_ROD_ARGS are passed to build_fmu.py, e.g. --fmi-version 3)
#   make clean   remove build/test/demo outputs (keeps .venv; `make distclean` removes it too)
#
# Variables: VERBOSE=1 shows colcon's full output; PYTEST_ARGS, DEMO_ARGS, BENCH_SCALE_ARGS are
# passed through.

SHELL := /bin/bash
.DEFAULT_GOAL := build

ROOT := $(patsubst %/,%,$(dir $(abspath $(lastword $(MAKEFILE_LIST)))))
VENV := $(ROOT)/.venv
PY := $(VENV)/bin/python
COLCON := $(VENV)/bin/colcon
STAMP := $(VENV)/.requirements.stamp
WS := $(ROOT)/ros_ws
PACKAGES := sep_plant sep_estimator sep_control

# Interpreter used only to create the venv: the ROS 2 Jazzy wheels in requirements.txt are
# built for CPython 3.11, so prefer it; fall back to python3.
BASE_PYTHON ?= $(shell for p in python3.11 python3; do \
	  if $$p -c 'import sys; sys.exit(sys.version_info < (3, 10))' >/dev/null 2>&1; then \
	    command -v $$p; break; fi; done)

# Test folders that exist (ament_python keeps per-package tests in <pkg>/test/).
TEST_DIRS := $(foreach d,tests $(addsuffix /test,$(PACKAGES)),$(if $(wildcard $(ROOT)/$(d)),$(d)))
BENCHES := $(sort $(filter-out %/bench_scale.py,$(wildcard $(ROOT)/bench/*.py)))
# Package source roots, so that bench scripts import the pure modules without installing.
empty :=
space := $(empty) $(empty)
SRC_PYTHONPATH := $(subst $(space),:,$(addprefix $(ROOT)/,$(PACKAGES)))

# Byte-compile the install space (an inherited PYTHONDONTWRITEBYTECODE only makes setuptools
# print "byte-compiling is disabled" warnings); logs stay inside the workspace.
COLCON_BUILD := PYTHONDONTWRITEBYTECODE= $(COLCON) --log-base $(WS)/log build \
	--base-paths $(WS)/src --build-base $(WS)/build --install-base $(WS)/install

.PHONY: all venv build test demo bench bench-scale fmu-rod clean distclean

all: build

venv: $(STAMP)

# The worked example of a user's own plant (examples/burgers): installed into the venv like a
# user would install theirs, so its `sep.plants` entry point is found (and tested).
EXAMPLE_PLANTS := $(ROOT)/examples/burgers

# Re-run pip whenever requirements.txt changes; the stamp lives inside .venv, so removing
# .venv also forces a fresh install.
$(STAMP): $(ROOT)/requirements.txt $(addsuffix /pyproject.toml,$(EXAMPLE_PLANTS))
	@if [ ! -x "$(PY)" ]; then \
	  if [ -z "$(BASE_PYTHON)" ]; then echo "error: need python3.11 (or python3 >= 3.10) to create .venv" >&2; exit 1; fi; \
	  echo "creating $(VENV) with $(BASE_PYTHON)"; \
	  "$(BASE_PYTHON)" -m venv "$(VENV)"; \
	fi
	"$(PY)" -m pip install --disable-pip-version-check --progress-bar off -q -r "$(ROOT)/requirements.txt"
	"$(PY)" -m pip install --disable-pip-version-check --progress-bar off -q --no-deps $(addprefix -e ,$(EXAMPLE_PLANTS))
	@touch "$@"

build: venv
ifeq ($(VERBOSE),1)
	cd "$(WS)" && $(COLCON_BUILD)
else
	@mkdir -p "$(WS)/log"
	@cd "$(WS)" && if ! $(COLCON_BUILD) > log/colcon_build.out 2>&1; then \
	  cat log/colcon_build.out; echo "error: colcon build failed (output above)" >&2; exit 1; fi; \
	grep -E '^(Starting|Finished|Failed)|[Ww]arning|WARNING|ERROR' log/colcon_build.out || true
endif

test: build
	@if [ -z "$(strip $(TEST_DIRS))" ]; then echo "error: no test folders found" >&2; exit 1; fi
	@cd "$(ROOT)" && "$(PY)" -m pytest -q $(TEST_DIRS) $(PYTEST_ARGS); rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "error: pytest collected no tests" >&2; fi; exit $$rc

demo: build
	cd "$(ROOT)" && . ros_ws/install/setup.sh && ros_ws/install/sep_control/lib/sep_control/demo --out out/demo $(DEMO_ARGS)

bench: venv
	@if [ -z "$(BENCHES)" ]; then echo "no benchmarks in bench/"; exit 0; fi; \
	cd "$(ROOT)" && for b in $(BENCHES); do \
	  echo "== $${b#$(ROOT)/}"; \
	  PYTHONPATH="$(SRC_PYTHONPATH)$${PYTHONPATH:+:$$PYTHONPATH}" "$(PY)" "$$b" || exit 1; \
	done; \
	echo "== bench/bench_scale.py --quick"; \
	PYTHONPATH="$(SRC_PYTHONPATH)$${PYTHONPATH:+:$$PYTHONPATH}" "$(PY)" bench/bench_scale.py --quick

bench-scale: venv
	cd "$(ROOT)" && OPENBLAS_NUM_THREADS=1 PYTHONPATH="$(SRC_PYTHONPATH)$${PYTHONPATH:+:$$PYTHONPATH}" \
	  "$(PY)" bench/bench_scale.py $(BENCH_SCALE_ARGS)

fmu-rod: venv
	cd "$(ROOT)" && "$(PY)" examples/fmu_rod/build_fmu.py --out examples/fmu_rod/rod.fmu $(FMU_ROD_ARGS)

clean:
	rm -rf "$(WS)/build" "$(WS)/install" "$(WS)/log" "$(ROOT)/out" "$(ROOT)/.pytest_cache"
	find "$(ROOT)" -path "$(VENV)" -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +

distclean: clean
	rm -rf "$(VENV)"
