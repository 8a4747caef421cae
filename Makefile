# Two commands do all the set-up on a fresh machine: `make train` and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: train test lint bench clean-venv

# Re-install only when the dependency list or the constraints change.
$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt torch==2.13.0
	@# setuptools warns on every editable install that same-named folders may shadow the package: nothing to act on
	PYTHONWARNINGS="ignore:Editable installation" $(PY) -m pip install --quiet -c constraints.txt -e ".[dev,cluster]"
	@if $(PY) -m pip list 2>/dev/null | grep -qi nvidia; then echo "error: CUDA packages were installed" >&2; exit 1; fi
	touch $(STAMP)

.venv: $(STAMP)

train: $(STAMP)
	$(PY) train.py fit --config configs/default.yaml

# Pass 1: the whole suite with one torch/BLAS thread per process, in two processes side by side (one per core
# of a 2-core machine): the slow end-to-end tests (marker slow; output in .pytest_tmp/slow.log, shown at the
# end) and the rest. Pass 2, after the rest: the tests whose verdict depends on float reduction order (marker
# reduction_order, listed in tests/reduction_order.py) again with two threads and torch's portable (non-SIMD)
# CPU kernels (ATEN_CPU_CAPABILITY=default, oneDNN limited to SSE4.1): other reduction orders, as on another
# CPU, so a test that only passes bit for bit here fails here first. OpenMP threads sleep when idle
# (OMP_WAIT_POLICY=PASSIVE): spinning threads slow everything on a shared 2-core machine.
ONE_THREAD := DACR_TEST_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 OMP_WAIT_POLICY=PASSIVE
OTHER_ORDER := DACR_TEST_THREADS=2 OMP_NUM_THREADS=2 OPENBLAS_NUM_THREADS=2 OMP_WAIT_POLICY=PASSIVE \
	ATEN_CPU_CAPABILITY=default ONEDNN_MAX_CPU_ISA=SSE41 DACR_TEST_AOTI=0

test: $(STAMP)
	$(PY) -m ruff check .
	@rm -rf .pytest_tmp && mkdir .pytest_tmp
	@echo "pass 1: the slow tests run beside the others (output at the end); then pass 2 (-m reduction_order)"
	@$(ONE_THREAD) $(PY) -m pytest -q -m slow -p no:cacheprovider --basetemp=.pytest_tmp/slow \
		> .pytest_tmp/slow.log 2>&1 & slow=$$!; \
	$(ONE_THREAD) $(PY) -m pytest -q -m "not slow" --basetemp=.pytest_tmp/rest; rest=$$?; \
	echo "pass 2: the reduction_order tests, two threads, portable kernels"; \
	$(OTHER_ORDER) $(PY) -m pytest -q -m reduction_order -p no:cacheprovider --basetemp=.pytest_tmp/pass2; \
	pass2=$$?; wait $$slow; slow=$$?; \
	echo "pass 1, the slow tests (.pytest_tmp/slow.log):"; cat .pytest_tmp/slow.log; \
	test $$rest -eq 0 && test $$pass2 -eq 0 && test $$slow -eq 0

lint: $(STAMP)
	$(PY) -m ruff check .

bench: $(STAMP)
	$(PY) benchmarks/kinematics.py

clean-venv:
	rm -rf $(VENV)
