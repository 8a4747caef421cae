# Two commands do all the set-up on a fresh machine: `make train` and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: train test lint bench cpp clean-venv

# Re-install only when the dependency list or the constraints change.
$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet --no-compile -c constraints.txt torch==2.13.0
	@# Byte-compiled on all cores (pip compiles on one core only): what is installed so far (torch and its dependencies:
	@# most of the compiling) in the background while pip installs the rest (on one core), then what pip added. A file
	@# written for a newer Python (torch's testing/_internal/py312_intrinsics.py) does not compile, as under pip, and is
	@# never imported. setuptools warns on every editable install that same-named folders may shadow the package:
	@# nothing to act on.
	@purelib="$$($(PY) -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"; \
	$(PY) -m compileall -q -j 0 "$$purelib"/* > /dev/null 2>&1 & compiling=$$!; \
	PYTHONWARNINGS="ignore:Editable installation" $(PY) -m pip install --quiet --no-compile -c constraints.txt \
		-e ".[dev,cluster]"; installed=$$?; wait $$compiling; test $$installed -eq 0 && \
	{ $(PY) -m compileall -q -j 0 "$$purelib" > /dev/null 2>&1 || true; }
	@if $(PY) -m pip list 2>/dev/null | grep -qi nvidia; then echo "error: CUDA packages were installed" >&2; exit 1; fi
	touch $(STAMP)

.venv: $(STAMP)

train: $(STAMP)
	$(PY) train.py fit --config configs/default.yaml

# Pass 1: the whole suite with one torch/BLAS thread per process, in two processes side by side (one per core
# of a 2-core machine): the slow end-to-end tests (marker slow) and the rest. Pass 2, in each process after its
# pass-1 share: the tests whose verdict depends on float reduction order (marker reduction_order, listed in
# tests/reduction_order.py, split between the two processes by marker second_pass_beside_slow so that both end
# together) again with two threads and torch's portable (non-SIMD) CPU kernels (ATEN_CPU_CAPABILITY=default,
# oneDNN limited to SSE4.1): other reduction orders, as on another CPU, so a test that only passes bit for bit
# here fails here first. The slow process's output goes to .pytest_tmp/slow.log, shown at the end. OpenMP
# threads sleep when idle (OMP_WAIT_POLICY=PASSIVE): spinning threads slow everything on a shared 2-core machine.
# Pass 2 collects only the modules tests/reduction_order.py lists. Bytecode is written even where the environment
# says otherwise (PYTHONDONTWRITEBYTECODE): the later processes and every subprocess a test starts then import the
# tests' assertion-rewritten modules and the library from __pycache__ instead of compiling them again.
# Each process's passes share a folder of exports (DACR_TEST_EXPORTS, tests/conftest.py first_pass_export): the
# second pass runs the programs the first pass exported, against its own eager results, instead of tracing them again.
ONE_THREAD := DACR_TEST_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 OMP_WAIT_POLICY=PASSIVE
OTHER_ORDER := DACR_TEST_THREADS=2 OMP_NUM_THREADS=2 OPENBLAS_NUM_THREADS=2 OMP_WAIT_POLICY=PASSIVE \
	ATEN_CPU_CAPABILITY=default ONEDNN_MAX_CPU_ISA=SSE41 DACR_TEST_AOTI=0
PYTEST := PYTHONDONTWRITEBYTECODE= $(PY) -m pytest -q -p no:cacheprovider

test: $(STAMP)
	$(PY) -m ruff check .
	@rm -rf .pytest_tmp && mkdir .pytest_tmp
	@echo "two processes: the slow tests, then their share of pass 2 (output at the end) | the rest, then pass 2"
	@( export DACR_TEST_EXPORTS=.pytest_tmp/exports_slow; $(ONE_THREAD) $(PYTEST) -m slow --basetemp=.pytest_tmp/slow; one=$$?; \
	  echo "pass 2 (beside the slow tests): two threads, portable kernels"; \
	  $(OTHER_ORDER) $(PYTEST) -m "reduction_order and second_pass_beside_slow" --basetemp=.pytest_tmp/slow2 \
	    $$($(PY) tests/reduction_order.py beside); \
	  two=$$?; test $$one -eq 0 && test $$two -eq 0 ) > .pytest_tmp/slow.log 2>&1 & slow=$$!; \
	export DACR_TEST_EXPORTS=.pytest_tmp/exports_rest; \
	$(ONE_THREAD) $(PYTEST) -m "not slow" --basetemp=.pytest_tmp/rest; rest=$$?; \
	echo "pass 2: the reduction_order tests, two threads, portable kernels"; \
	$(OTHER_ORDER) $(PYTEST) -m "reduction_order and not second_pass_beside_slow" --basetemp=.pytest_tmp/pass2 \
	  $$($(PY) tests/reduction_order.py rest); \
	pass2=$$?; wait $$slow; slow=$$?; \
	echo "the slow tests and their share of pass 2 (.pytest_tmp/slow.log):"; cat .pytest_tmp/slow.log; \
	test $$rest -eq 0 && test $$pass2 -eq 0 && test $$slow -eq 0

lint: $(STAMP)
	$(PY) -m ruff check .

# The C++ library and examples (cpp/, docs/cpp.md) against the libtorch inside the installed torch wheel: cmake and a
# C++ compiler (ninja if present); a missing one is a one-line error naming it.
cpp: $(STAMP)
	@PYTHON=$(PY) cpp/build.sh

bench: $(STAMP)
	$(PY) benchmarks/kinematics.py

clean-venv:
	rm -rf $(VENV)
