# sep: build, test and demo entry points.  `make test` is the one test command.
#
#   make venv    create .venv with $(PYTHON) (see below), install requirements.txt and the
#                example plant package (examples/burgers)
#   make build   colcon build of ros_ws/ (the ros2-run layout under ros_ws/install), then put
#                `sep` on the venv's PATH (`. .venv/bin/activate`), running that install
#   make test    build, then pytest over tests/ and every <pkg>/test/ that exists
#   make demo    build, then `sep demo` from the install space
#   make bench   run every bench/*.py with the venv python (bench_scale.py as --quick)
#   make bench-scale  bench/bench_scale.py: the scaling table across plants and grids (long;
#                BENCH_SCALE_ARGS=--quick for the small rows)
#   make fmu-rod build the example FMU examples/fmu_rod/rod.fmu from its C source (needs cc/gcc;
#                FMU_ROD_ARGS are passed to build_fmu.py, e.g. --fmi-version 3)
#   make clean   remove build/test/demo outputs and the venv's `sep` (keeps .venv;
#                `make distclean` removes it too)
#
# Variables: PYTHON=python3.12 chooses the interpreter that creates .venv (default: the first
# of python3.11, python3.12, python3 that is a supported version); VERBOSE=1 shows colcon's full
# output; PYTEST_ARGS, DEMO_ARGS, BENCH_SCALE_ARGS are passed through.

SHELL := /bin/bash
.DEFAULT_GOAL := build

ROOT := $(patsubst %/,%,$(dir $(abspath $(lastword $(MAKEFILE_LIST)))))
VENV := $(ROOT)/.venv
PY := $(VENV)/bin/python
COLCON := $(VENV)/bin/colcon
STAMP := $(VENV)/.requirements.stamp
WS := $(ROOT)/ros_ws
PACKAGES := sep_plant sep_estimator sep_control

# Interpreter used only to create the venv.  Every pin of requirements.txt and its whole
# dependency closure (the ROS 2 Jazzy wheels included; EmPy is pure Python) have wheels for
# CPython 3.11 and 3.12 (Jazzy's, on Ubuntu 24.04), and both are tested; numpy 2.4 needs
# >= 3.11.  3.11 stays first when both are there.  3.13 resolves too but is not tested:
# `make PYTHON=python3.13 SUPPORTED_PYTHONS=3.13` to try it.
SUPPORTED_PYTHONS ?= 3.11 3.12
PY_VERSION_OF = $(1) -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null
ifeq ($(strip $(PYTHON)),)
PYTHON := $(shell for p in python3.11 python3.12 python3; do \
	  v=$$($(call PY_VERSION_OF,$$p)) || continue; \
	  case " $(SUPPORTED_PYTHONS) " in (*" $$v "*) command -v $$p; break;; esac; done)
endif

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

.PHONY: all venv check-python build test demo bench bench-scale fmu-rod clean distclean

all: build

venv: $(STAMP)

# The worked example of a user's own plant (examples/burgers): installed into the venv like a
# user would install theirs, so its `sep.plants` entry point is found (and tested).
EXAMPLE_PLANTS := $(ROOT)/examples/burgers

# Re-run pip whenever requirements.txt changes; the stamp lives inside .venv, so removing
# .venv also forces a fresh install.
$(STAMP): $(ROOT)/requirements.txt $(ROOT)/requirements-controlgym.txt $(addsuffix /pyproject.toml,$(EXAMPLE_PLANTS)) | check-python
	@if [ ! -x "$(PY)" ]; then \
	  echo "creating $(VENV) with $(PYTHON) (Python $$($(call PY_VERSION_OF,"$(PYTHON)")))"; \
	  "$(PYTHON)" -m venv "$(VENV)"; \
	fi
	"$(PY)" -m pip install --disable-pip-version-check --progress-bar off -q -r "$(ROOT)/requirements.txt"
	"$(PY)" -m pip install --disable-pip-version-check --progress-bar off -q --no-deps -r "$(ROOT)/requirements-controlgym.txt"
	"$(PY)" -m pip install --disable-pip-version-check --progress-bar off -q --no-deps $(addprefix -e ,$(EXAMPLE_PLANTS))
	@touch "$@"

# Stops at once, before anything is created, when the interpreter cannot make a working venv:
# none found, not runnable, not a supported version, or (PYTHON given) not the existing venv's.
HOW_TO_GET_PYTHON := install python3.12 (Ubuntu 24.04's python3) or python3.11 (pyenv, or the \
deadsnakes PPA on Ubuntu) and run \`PYTHON=python3.12 make\`; on a native ROS 2 Jazzy install \
use the system python3 with requirements-ros.txt instead (see that file)
check-python:
	@fail() { echo "error: $$*; $(HOW_TO_GET_PYTHON)" >&2; exit 2; }; \
	if [ -x "$(PY)" ]; then \
	  have=$$($(call PY_VERSION_OF,"$(PY)")); \
	  case "$(origin PYTHON)" in environment|command*) \
	    want=$$($(call PY_VERSION_OF,"$(PYTHON)")); \
	    if [ "$$want" != "$$have" ]; then \
	      echo "error: $(VENV) uses Python $$have, PYTHON=$(PYTHON) is $${want:-not runnable}:" \
	        "run \`make distclean\` first to recreate it" >&2; exit 2; fi;; \
	  esac; \
	elif [ -z "$(PYTHON)" ]; then \
	  fail "no python3.11 or python3.12 found to create $(VENV) (supported: $(SUPPORTED_PYTHONS))"; \
	else \
	  v=$$($(call PY_VERSION_OF,"$(PYTHON)")) || fail "PYTHON=$(PYTHON) does not run"; \
	  case " $(SUPPORTED_PYTHONS) " in *" $$v "*) ;; *) \
	    fail "PYTHON=$(PYTHON) is Python $$v; the pinned requirements (ROS 2 Jazzy wheels" \
	      "from PyPI, numpy 2.4) are tested on Python $(SUPPORTED_PYTHONS)";; \
	  esac; \
	fi

# After colcon: `sep` on the activated venv's PATH, running ros_ws/install (the same copy as the
# ROS executables): ros_ws/link_venv.sh writes .venv/bin/sep and a .pth file (see there).
build: venv
ifeq ($(VERBOSE),1)
	cd "$(WS)" && $(COLCON_BUILD)
else
	@mkdir -p "$(WS)/log"
	@cd "$(WS)" && if ! $(COLCON_BUILD) > log/colcon_build.out 2>&1; then \
	  cat log/colcon_build.out; echo "error: colcon build failed (output above)" >&2; exit 1; fi; \
	grep -E '^(Starting|Finished|Failed)|[Ww]arning|WARNING|ERROR' log/colcon_build.out || true
endif
	@sh "$(WS)/link_venv.sh" "$(VENV)" "$(WS)/install" $(PACKAGES)

test: build
	@if [ -z "$(strip $(TEST_DIRS))" ]; then echo "error: no test folders found" >&2; exit 1; fi
	@cd "$(ROOT)" && "$(PY)" -m pytest -q $(TEST_DIRS) $(PYTEST_ARGS); rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "error: pytest collected no tests" >&2; fi; exit $$rc

demo: build
	cd "$(ROOT)" && "$(VENV)/bin/sep" demo --out out/demo $(DEMO_ARGS)

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
	sh "$(WS)/link_venv.sh" --remove "$(VENV)"
	find "$(ROOT)" -path "$(VENV)" -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +

distclean: clean
	rm -rf "$(VENV)"
