# The two commands of the README. Both work on a fresh machine with python3 >= 3.11 and venv.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO_OUT ?= runs/demo

.PHONY: demo test lint bench results beyond sweeps docs docs-serve clean

# numpy's AVX-512 tan/arctan differ from libm's in the last bit; the fast simulator (numba → libm)
# matches highway-env bit for bit only with numpy on libm (safelane.sim.fast.libm). Ignored elsewhere.
export NPY_DISABLE_CPU_FEATURES ?= X86_V4 AVX512_ICL AVX512_SPR
# OpenBLAS's AVX-512 ddot fuses multiply-adds (LinearVehicle's np.dot steering): keep it on SSE kernels (libm.py).
export OPENBLAS_CORETYPE ?= Nehalem

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip

# torch first, pinned: an unpinned torch pulls a multi-GB CUDA build.
# RL Zoo last, for tests/test_registration.py, without its requirements: they pin pillow<12 (moviepy, through
# sb3-team-hf-integration's video upload) and python-dateutil<3 (typepy, through pytablewriter's benchmark
# tables), and would downgrade both. Its train script imports neither; what it does import is in the test extra.
$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[test]'
	$(BIN)/pip install --quiet --no-deps rl_zoo3==2.9.2 sb3-team-hf-integration==3.2
	touch $(STAMP)

# The paper's protocol at scale on the fast simulator: 4 methods x 10 seeds x 200 training episodes,
# 1 000 held-out test episodes per run (≈ 2.5 min on 2 cores once installed, the runs trained as batched learners; `safelane reproduce --quick` is the
# minutes-long version the tests use).
demo: $(STAMP)
	SDL_VIDEODRIVER=dummy $(BIN)/safelane reproduce --simulator fast --seeds 10 --episodes 200 \
		--test-episodes 1000 --out $(DEMO_OUT)

# The tests include tests/test_docs.py: the strict site build and every example of the README and the guides.
# Two workers (pytest-xdist), a test file per worker: the CI machine has two cores and most tests use one
# (measured from a clean clone on this project's 2-core machine: 737-832 s in one process, 436 s on two workers).
# TEST_WORKERS=0 runs them in one process.
TEST_WORKERS ?= 2
test: $(STAMP)
	$(BIN)/ruff check src tests examples research docs/_ext
	$(BIN)/lint-imports
	SDL_VIDEODRIVER=dummy $(BIN)/python -m pytest -q -m "not slow" --durations=25 -n $(TEST_WORKERS) --dist loadfile

lint: $(STAMP)
	$(BIN)/ruff check src tests examples research docs/_ext
	$(BIN)/lint-imports

# The documentation site (mkdocs.yml, docs/): built strictly into site/, or served with live reload.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --site-dir site

docs-serve: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs serve

bench: $(STAMP)
	$(BIN)/safelane bench

# The README's tables, in full (hours on 2 cores; a re-run skips finished runs, so it resumes).
# results: the paper's protocol, 4 methods x 5 seeds. beyond: robust Q-masking at 3 decisions/s with the
# lane state; gamma, buffer, target interval, learning start and Q-shaping margin scaled to keep their
# length in seconds (README, "Beyond the paper").
results: $(STAMP)
	SDL_VIDEODRIVER=dummy $(BIN)/safelane reproduce --preset fast --seeds 5 --episodes 200 \
		--test-episodes 100 --workers 2 --out runs/results

beyond: $(STAMP)
	SDL_VIDEODRIVER=dummy $(BIN)/safelane reproduce --methods robust --preset fast --seeds 5 --episodes 200 \
		--test-episodes 100 --workers 2 --out runs/beyond3m --set state=lanes \
		--set env.policy_frequency=3 --set env.simulation_frequency=15 --set agent.gamma=0.965 \
		--set agent.buffer_size=45000 --set agent.target_update_interval=600 --set agent.learning_starts=600 \
		--set agent.shaping_margin=0.033

# The paper's four grid searches and the robust one by TPE (configs/sweeps/), 3 seeds per point on the
# fast simulator.
sweeps: $(STAMP)
	for spec in configs/sweeps/*.yaml; do \
		$(BIN)/safelane sweep $$spec --out runs/sweeps/$$(basename $$spec .yaml) || exit 1; \
	done

clean:
	rm -rf $(VENV) build site *.egg-info src/*.egg-info
