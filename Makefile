# aerial_loc_env: every target creates its own virtual environment in .venv on a fresh machine.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
# The CPU build of torch: pinned so that pip never pulls several GB of CUDA packages.
TORCH  ?= torch==2.13.0

.PHONY: venv run test test-fast bench bench-avx2 pictures lint wheel clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	$(PIP) install -q "$(TORCH)"
	# cv2 comes from opencv-contrib-python-headless; the plain package writes the same files: never both
	$(PIP) uninstall -q -y opencv-python-headless opencv-python
	$(PIP) install -q -e ".[test,rl,data,mavlink,plots,ray]"
	touch $@

venv: $(VENV)/.installed

## Quick start 1: install, then run the main job on the embedded default map.
run: venv
	$(VENV)/bin/aerial-loc bench

## Quick start 2: install, then run the whole test suite: on 2 workers, then the tests timed by the wall clock
## (real UDP links, SITL missions; marked realtime) alone, as a loaded machine would stretch their update gaps.
test: venv
	$(PY) -m pytest -q -n 2 -m "not realtime"
	$(PY) -m pytest -q -m realtime

# The developer's loop: the suite without the tests marked slow (statistical, training, long flights, the ones
# that take seconds: fresh interpreters, worker processes, every id or agent, the behaviour digests).
test-fast: venv
	$(PY) -m pytest -q -m "not slow" -n 2

# Speed benchmarks on one core (BLAS/OpenMP pinned before numpy loads).
bench: venv
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 $(PY) -m aerial_loc_env.perf $(ARGS)

# The same, computed as an AVX2 machine without AVX-512 does (numba, NumPy, OpenCV, OpenBLAS), on any x86-64 host.
bench-avx2: venv
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 $(PY) -m aerial_loc_env.perf --avx2 $(ARGS)

# with ../shared, a real LEVIR-CD pair beside the simulated gap (in results/pictures, never docs/img: its licence
# forbids copies in the repository)
LEVIR  := ../shared/data/pairs/levir-cd
pictures: venv
	$(VENV)/bin/aerial-loc pictures --out results/pictures --realism --readme-dir docs/img
	$(if $(wildcard $(LEVIR)/A/test_1.png),$(VENV)/bin/aerial-loc pictures --out results/pictures --frames 1 --realism \
		--pair $(LEVIR)/A/test_1.png $(LEVIR)/B/test_1.png --pair-gsd 0.5)

lint: venv
	$(VENV)/bin/ruff check aerial_loc_env tests

wheel: venv
	$(PIP) install -q build
	$(PY) -m build --wheel --outdir dist

clean:
	rm -rf $(VENV) dist build .pytest_cache
