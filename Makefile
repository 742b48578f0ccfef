# The two commands of the README. Both work on a fresh machine with python3 >= 3.11 and venv.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO_OUT ?= runs/demo

.PHONY: demo test lint bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip

# torch first, pinned: an unpinned torch pulls a multi-GB CUDA build.
$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	SDL_VIDEODRIVER=dummy $(BIN)/safelane reproduce --quick --out $(DEMO_OUT)

test: $(STAMP)
	$(BIN)/ruff check src tests
	SDL_VIDEODRIVER=dummy $(BIN)/python -m pytest -q -m "not slow"

lint: $(STAMP)
	$(BIN)/ruff check src tests

bench: $(STAMP)
	$(BIN)/safelane bench

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info
