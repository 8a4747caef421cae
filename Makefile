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

# The suite runs once with one torch/BLAS thread; then the tests whose verdict depends on float reduction
# order (marker reduction_order, listed in tests/reduction_order.py) run again with two threads and torch's
# portable (non-SIMD) CPU kernels (ATEN_CPU_CAPABILITY=default, oneDNN limited to SSE4.1): other reduction
# orders, as on another CPU, so a test that only passes bit for bit here fails here first. OpenMP threads
# sleep when idle (OMP_WAIT_POLICY=PASSIVE): spinning threads slow everything on a shared 2-core machine.
test: $(STAMP)
	$(PY) -m ruff check .
	DACR_TEST_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 OMP_WAIT_POLICY=PASSIVE $(PY) -m pytest -q
	DACR_TEST_THREADS=2 OMP_NUM_THREADS=2 OPENBLAS_NUM_THREADS=2 OMP_WAIT_POLICY=PASSIVE ATEN_CPU_CAPABILITY=default ONEDNN_MAX_CPU_ISA=SSE41 \
		DACR_TEST_AOTI=0 $(PY) -m pytest -q -m reduction_order -p no:cacheprovider

lint: $(STAMP)
	$(PY) -m ruff check .

bench: $(STAMP)
	$(PY) benchmarks/kinematics.py

clean-venv:
	rm -rf $(VENV)
